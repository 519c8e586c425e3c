"""Objectives of the contrast core: ``objective(batch, params) -> (B,)``, lower is better, differentiable.

Each objective is a small frozen dataclass holding its settings; calling it
with an :class:`~cmax.contrast.batch.EventWindows` batch of B windows and the
parameters of each window (:class:`DepthMotion`: an inverse-depth map on any
grid up to the sensor size and a twist) returns one value per window, a
tensor (B,) differentiable with respect to both. When the batch carries the
known speed of each window, every objective first rescales the twist's ``v``
to that norm (:func:`twist_at_speed`): the contrast sees only inverse depth
times speed, and the known speed is what makes the depth metric.

The shared depth-and-motion objective (the one :mod:`learned` trains on and
the fit's final refinement can optimise) is :data:`SHARED_OBJECTIVE`, an
:class:`AverageTimestamp`; ``docs/contrast_objective.md`` says why.

Warping convention (:mod:`cmax.warp`): an event at pixel ``x_i``, time
``t_i`` is moved to the reference time with the inverse depth read at its
own pixel (bilinear on the depth grid, :class:`cmax.warp.DepthGrid`).
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
import numbers
from dataclasses import dataclass
from typing import NamedTuple

import torch

from cmax.contrast._timestamp_kernels import EDGE_TOLERANCE_PX, average_timestamp_images, compiled_images_apply
from cmax.contrast._warp_kernels import compiled_warp_applies, warp_se3_compiled
from cmax.contrast.batch import EventWindows
from cmax.iwe import _finite_corner, accumulate_bilinear_indexed, blur
from cmax.objectives import contrast_of_images, deformation, local_contrast, total_variation
from cmax.warp import DepthGrid, project, se3_parts, warp_se3

__all__ = [
    "DepthMotion", "twist_at_speed", "event_inverse_depth", "warp_windows", "log_depth_variation",
    "AverageTimestamp", "SweepVote", "PlaneVote", "VoteNormaliser", "CrossFit", "HeldOutSplit", "LocalContrast",
    "GlobalContrast",
    "CollapseGuard", "WeightedSum", "SHARED_OBJECTIVE",
]

#: CPU float32 / float64 batches take the compiled images of :mod:`cmax.contrast._timestamp_kernels` and the
#: compiled warp of :mod:`cmax.contrast._warp_kernels` in :class:`AverageTimestamp`;
#: False: the torch operations everywhere (the reference; for tests and benchmarks).
_COMPILED = True

#: Probe times of the deformation guard, in units of the window duration (as in ``cmax.fit``).
PROBE_TIMES = (-1.0, -0.5, 0.5, 1.0)


@dataclass(frozen=True, eq=False)
class DepthMotion:
    """Parameters of B windows: inverse depth and twist.

    Attributes
    ----------
    inverse_depth : Tensor (B, 1, h, w)
        Inverse z-depth [1/m] (>= 0) on a grid of nodes over the image
        (:class:`cmax.warp.DepthGrid`; ``h, w = H, W``: a per-pixel map).
    twist : Tensor (B, 6)
        ``(v [m/s], omega [rad/s])``, camera frame, constant over the window.
    """

    inverse_depth: torch.Tensor
    twist: torch.Tensor

    def __post_init__(self) -> None:
        if self.inverse_depth.dim() != 4 or self.inverse_depth.shape[1] != 1:
            raise ValueError(f"inverse_depth must have shape (B, 1, h, w), got {tuple(self.inverse_depth.shape)}")
        if self.twist.shape != (self.inverse_depth.shape[0], 6):
            raise ValueError(f"twist must have shape ({self.inverse_depth.shape[0]}, 6) (v m/s, omega rad/s), "
                             f"got {tuple(self.twist.shape)}")


def _check(batch: EventWindows, params: DepthMotion) -> None:
    if not isinstance(batch, EventWindows):
        raise TypeError(f"batch must be a cmax.contrast.EventWindows, got {type(batch).__name__}")
    if not isinstance(params, DepthMotion):
        raise TypeError(f"params must be a cmax.contrast.DepthMotion, got {type(params).__name__}")
    if params.twist.shape[0] != batch.count:
        raise ValueError(f"params hold {params.twist.shape[0]} windows, the batch {batch.count}")
    h, w = params.inverse_depth.shape[-2:]
    if h > batch.height or w > batch.width:
        raise ValueError(f"inverse_depth grid {h}x{w} is finer than the image {batch.height}x{batch.width}")
    if len(batch) == 0:
        raise ValueError("batch: holds no events")


def _require_int(owner: str, name: str, value: object, minimum: int) -> None:
    """``owner.name`` must be an integer (not a bool) >= ``minimum``, else a ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise ValueError(f"{owner}: {name} must be an integer >= {minimum}, got {value!r}")


def _require_number(owner: str, name: str, value: object, minimum: float | None = None, *,
                    above: bool = False) -> None:
    """``owner.name`` must be a finite number, ``>= minimum`` (``> minimum`` with ``above``) when given, else a
    ValueError naming it (NaN, a negative blur or a zero ``eps`` gave NaN, a silently unblurred image or a
    ZeroDivisionError at the first call)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and minimum is not None:
        ok = value > minimum if above else value >= minimum
    if not ok:
        bound = "" if minimum is None else f" {'>' if above else '>='} {minimum:g}"
        raise ValueError(f"{owner}: {name} must be a finite number{bound}, got {value!r}")


def _require_cross_fit(owner: str, cross_fit: object) -> None:
    """``owner.cross_fit`` must be None or a :class:`CrossFit`, else a ValueError naming it (a string such as
    ``"random"`` was accepted and failed with an AttributeError at the first call)."""
    if cross_fit is not None and not isinstance(cross_fit, CrossFit):
        raise ValueError(f"{owner}: cross_fit must be None or a CrossFit (e.g. CrossFit('random')), got {cross_fit!r}")


def _require_grid(owner: str, name: str, value: object, minimum: int) -> None:
    """``owner.name`` must be two integers >= ``minimum`` (rows, cols)."""
    if not (isinstance(value, (tuple, list)) and len(value) == 2):
        raise ValueError(f"{owner}: {name} must be two integers >= {minimum} (rows, cols), got {value!r}")
    for n in value:
        _require_int(owner, f"{name} (rows, cols)", n, minimum)


def _non_finite_scores_nan(call):
    """Wrap an objective's ``__call__(batch, params)``: the inputs are checked (:func:`_check`), and a window whose
    twist or inverse depth holds a NaN or an infinity scores NaN (an optimiser or a network that produced it
    sees NaN, as from any torch operation, never a good-looking value; was: near the loss's minimum, or an
    ``IndexError`` from the images). The objective itself runs on the parameters with those entries set to 0,
    so nothing downstream indexes with NaN; the other windows' values and gradients are unchanged. No
    host-device synchronisation."""

    @functools.wraps(call)
    def wrapped(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        _check(batch, params)
        finite = (torch.isfinite(params.twist).all(1)
                  & torch.isfinite(params.inverse_depth).flatten(1).all(1))
        safe = DepthMotion(torch.nan_to_num(params.inverse_depth, nan=0.0, posinf=0.0, neginf=0.0),
                           torch.nan_to_num(params.twist, nan=0.0, posinf=0.0, neginf=0.0))
        loss = call(self, batch, safe)
        return torch.where(finite.to(loss.device), loss, torch.full_like(loss, math.nan))

    return wrapped


def twist_at_speed(twist: torch.Tensor, speed: torch.Tensor | None) -> torch.Tensor:
    """``twist`` (B, 6) with ``v`` rescaled to the norm ``speed`` (B,) [m/s]; unchanged when ``speed`` is None,
    and for the windows whose speed is NaN (unknown).

    Examples
    --------
    >>> import torch
    >>> twist_at_speed(torch.tensor([[3.0, 0, 4, 0, 0, 1]]), torch.tensor([10.0])).tolist()
    [[6.0, 0.0, 8.0, 0.0, 0.0, 1.0]]
    """
    if speed is None:
        return twist
    v = twist[:, :3]
    speed = speed.to(twist.dtype)[:, None]
    known = ~torch.isnan(speed)
    norm = torch.sqrt((v * v).sum(-1, keepdim=True) + 1e-24)
    scaled = v * (torch.where(known, speed, 0.0) / norm)
    return torch.cat([torch.where(known, scaled, v), twist[:, 3:]], -1)


def event_inverse_depth(batch: EventWindows, inverse_depth: torch.Tensor) -> torch.Tensor:
    """Inverse depth (N,) [1/m] of each event of ``batch``, read at its own pixel on its window's grid
    ``inverse_depth`` (B, 1, h, w) [1/m]."""
    index, weight = batch.grid_weights(tuple(inverse_depth.shape[-2:]))
    return DepthGrid.sample(inverse_depth.to(batch.dtype).reshape(-1), index, weight)


def warp_windows(batch: EventWindows, params: DepthMotion, dt: torch.Tensor, rays: torch.Tensor | None = None,
                 *, compiled: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Warped pixels (R, N) of every event for ``dt = t_i - t_ref`` (R, N) [s] (:func:`cmax.warp.warp_se3`,
    each event with its window's twist in ``params``, at the batch's speed, and intrinsics; ``rays`` (N, 3): the
    events' back-projected pixels when the caller has them, else computed). With ``compiled``, a CPU
    batch whose windows' events are contiguous runs is warped by
    :func:`cmax.contrast._warp_kernels.warp_se3_compiled`, window by window (equal to float rounding)."""
    dtype = batch.dtype
    b = batch.window
    rays = batch.rays() if rays is None else rays
    twists = twist_at_speed(params.twist.to(dtype), batch.speed)                 # (B, 6)
    rho = event_inverse_depth(batch, params.inverse_depth)
    bounds = batch.window_bounds() if compiled and rays.device.type == "cpu" else None
    if bounds is not None and all(compiled_warp_applies(rays, row, twists[0, :3], twists[0, 3:], rho) for row in dt):
        return _warp_compiled(batch, bounds, rays, dt, twists, rho)
    twist = twists[b]
    identity = torch.eye(3, dtype=dtype, device=rays.device)
    xn, yn = warp_se3(rays, dt, twist[:, :3], twist[:, 3:], rho, identity)
    K = batch.K.to(dtype)[b]
    return K[:, 0, 0] * xn + K[:, 0, 1] * yn + K[:, 0, 2], K[:, 1, 1] * yn + K[:, 1, 2]


def _warp_compiled(batch: EventWindows, bounds: tuple[tuple[int, int], ...], rays: torch.Tensor, dt: torch.Tensor,
                   twists: torch.Tensor, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`warp_windows` by :func:`cmax.contrast._warp_kernels.warp_se3_compiled`, window after window (each
    window's events a contiguous run ``bounds[b]``) and row after row of ``dt``."""
    xs, ys = [], []
    for row in dt:
        pieces = [warp_se3_compiled(rays[lo:hi], row[lo:hi], twists[b, :3], twists[b, 3:], rho[lo:hi], batch.K[b])
                  for b, (lo, hi) in enumerate(bounds) if hi > lo]
        xs.append(torch.cat([x for x, _ in pieces]))
        ys.append(torch.cat([y for _, y in pieces]))
    return torch.stack(xs), torch.stack(ys)


def log_depth_variation(inverse_depth: torch.Tensor, epsilon: float = 1e-3) -> torch.Tensor:
    """Smoothed total variation of ``log(inverse depth)`` (B, 1, h, w) per window (B,), in units that do not
    depend on the grid: the mean over nodes of ``sqrt(dx^2 + dy^2 + eps^2)`` times the grid's columns ``w``
    (a map of one depth and its grid-interpolated twin on a finer grid score about alike)."""
    log_rho = torch.log(inverse_depth.clamp(min=1e-6))[:, 0]
    width = inverse_depth.shape[-1]
    return torch.stack([total_variation(g, epsilon=epsilon) for g in log_rho]) * width


def _plus_smoothness(loss: torch.Tensor, smoothness: float, batch: EventWindows, params: DepthMotion
                     ) -> torch.Tensor:
    """``loss`` (B,) plus ``smoothness`` times :func:`log_depth_variation` of the inverse depth (none at 0)."""
    if smoothness > 0:
        loss = loss + smoothness * log_depth_variation(params.inverse_depth.to(batch.dtype))
    return loss


def _inside(batch: EventWindows, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    tol = EDGE_TOLERANCE_PX
    return (x >= -tol) & (x <= batch.width - 1 + tol) & (y >= -tol) & (y <= batch.height - 1 + tol)


@dataclass(frozen=True)
class AverageTimestamp:
    """Per-pixel average timestamp of the warped events, forward and backward (lower is better).

    Zhu, Yuan, Chaney, Daniilidis, "Unsupervised event-based learning of optical
    flow, depth, and egomotion", CVPR 2019, as refined by Hagenaars, Paredes-Vallés,
    de Croon, "Self-supervised learning of event-based optical flow with spiking
    neural networks", NeurIPS 2021. For each window and each reference time
    (``forward``: the window's end, the events weighted by their normalised time
    ``tau_i = t_i / T``; ``backward``: its start, weighted by ``1 - tau_i``) the
    events are warped there and imaged per polarity ``p`` with bilinear votes;
    the image of weighted votes over the image of votes is the average timestamp
    ``T_p(x)`` of each pixel, and

        L = sum_refs sum_x (T_+(x)^2 + T_-(x)^2) / #active pixels,

    with active pixels those with at least one vote. An event blurred over many
    pixels leaves pixels whose average is its own late timestamp; aligned, the
    early events dilute the late ones. Normalising by the number of active pixels
    (not by the events' count) keeps the loss from rewarding spreading events
    out; with ``purge`` (Hagenaars et al.) an event whose warp to either
    reference leaves the image is dropped from both, so pushing events out of
    the image cannot lower the loss.

    Zhu et al. and Hagenaars et al. add a smoothness term on the flow; here it is
    ``smoothness`` times the total variation of the log inverse depth
    (:func:`log_depth_variation`): without it a per-pixel map lets every pixel
    place its few events wherever they score best.

    With ``cross_fit`` (:class:`CrossFit`, ``random`` or ``pixels``; the held-out analogue) the events are dealt
    into folds and each fold imaged on its own: ``A^k_p(x)`` is the average timestamp of fold ``k``'s events,
    and ``T_p(x)^2`` becomes the mean over pairs of different folds of ``A^k_p(x) A^l_p(x)`` (with two folds,
    one half's timestamps read against the other half's per-pixel average: ``sum_x A^1 A^2 = sum_{i in 1}
    sum_x (share of event i in x) tau_i A^2(x)``), summed over the pixels where at least two folds vote in one
    polarity and divided by their number. An event's own timestamp is never squared: a pixel that holds one
    event (or the events of one fold) scores nothing instead of ``tau_i^2``; the product of two independent
    averages is the squared mean without the average's variance (the cross-fitting of Chernozhukov et al.,
    Econometrics Journal 2018, see :class:`CrossFit`). It takes the torch operations, not the compiled
    images.

    With ``references`` other than the end and the start (1, 0), the events are warped to each reference time
    ``r T`` and weighted by their closeness to it in time, ``1 - |tau_i - r| / max(r, 1 - r)`` (``tau_i`` at
    the end, ``1 - tau_i`` at the start), and the sum over references is scaled by ``2 / len(references)``
    (the smoothness weight keeps its meaning): the multi-reference focus of Shiba, Aoki, Gallego, "Secrets of
    event-based optical flow", ECCV 2022, applied to the average timestamp. Like ``cross_fit``, it takes the
    torch operations.

    Attributes
    ----------
    purge : bool
        Drop events that any warp moves out of the image.
    smoothness : float
        Weight of :func:`log_depth_variation` (0: none).
    eps : float
        Added to the vote count before dividing.
    cross_fit : CrossFit or None
        The held-out form above (``random`` or ``pixels`` split); None: each pixel's own average squared.
    references : tuple of float
        Reference times, fractions of the window in [0, 1] (distinct); (1, 0): the end and the start.
    """

    purge: bool = True
    smoothness: float = 0.0
    eps: float = 1e-9
    cross_fit: CrossFit | None = None
    references: tuple[float, ...] = (1.0, 0.0)

    def __post_init__(self) -> None:
        _require_number("AverageTimestamp", "smoothness", self.smoothness, 0.0)
        _require_number("AverageTimestamp", "eps", self.eps, 0.0, above=True)
        if self.cross_fit is not None and not (isinstance(self.cross_fit, CrossFit)
                                               and self.cross_fit.split is not HeldOutSplit.LEAVE_ONE_OUT):
            raise ValueError(f"AverageTimestamp: cross_fit must be None or a CrossFit with split 'random' or "
                             f"'pixels', got {self.cross_fit!r}")
        refs = self.references
        if not (isinstance(refs, tuple) and refs and len(set(refs)) == len(refs)
                and all(isinstance(r, numbers.Real) and not isinstance(r, bool) and 0 <= r <= 1 for r in refs)):
            raise ValueError(f"AverageTimestamp: references must be a non-empty tuple of distinct numbers in "
                             f"[0, 1] (fractions of the window), got {refs!r}")

    def _weights(self, tau: torch.Tensor) -> torch.Tensor:
        """Each event's weight (R, N) at each reference: its closeness in time (class docstring) for normalised
        times ``tau`` (N,) in [0, 1]; ``tau`` itself at the end, ``1 - tau`` at the start."""
        rows = [tau if r == 1 else 1.0 - tau if r == 0 else 1.0 - (tau - r).abs() / max(r, 1.0 - r)
                for r in self.references]
        return torch.stack(rows)

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        B, H, W, b = batch.count, batch.height, batch.width, batch.window
        duration = batch.duration_s.to(batch.dtype)[b]
        tau = (batch.t / duration).clamp(0.0, 1.0)
        R = len(self.references)
        dt = torch.stack([batch.t - duration if r == 1 else batch.t if r == 0 else batch.t - r * duration
                          for r in self.references])                            # (R, N); (1, 0): end, start
        x, y = warp_windows(batch, params, dt, compiled=_COMPILED)
        if self.cross_fit is not None:
            loss = self._held_out(batch, x, y, self._weights(tau)) * (2.0 / R)
            return _plus_smoothness(loss, self.smoothness, batch, params)
        if _COMPILED and self.references == (1.0, 0.0) and compiled_images_apply(x, y):
            base = (batch.polarity > 0).long() * B + b
            loss = average_timestamp_images(x, y, tau, base, B, (H, W), self.eps, self.purge)
            return _plus_smoothness(loss, self.smoothness, batch, params)
        keep = torch.ones_like(x)
        if self.purge:
            keep = _inside(batch, x.detach(), y.detach()).all(0).to(x.dtype).expand_as(x)
        weights = self._weights(tau)                                             # (R, N)
        on = (batch.polarity > 0).long()
        image = ((torch.arange(R, device=x.device)[:, None] * 2 + on[None]) * B + b[None]).reshape(-1)
        counts = accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), keep.reshape(-1), image, 2 * R * B, H, W)
        stamps = accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), (keep * weights).reshape(-1), image,
                                             2 * R * B, H, W)
        counts, stamps = counts.reshape(R, 2, B, H * W), stamps.reshape(R, 2, B, H * W)
        average = stamps / (counts + self.eps)
        square = (average * average).sum((1, 3))                              # (refs, B)
        active = (counts.detach().sum(1) > 0).sum(-1)                          # (refs, B)
        loss = (square / active.clamp(min=1).to(square.dtype)).sum(0) * (2.0 / R)
        return _plus_smoothness(loss, self.smoothness, batch, params)

    def _held_out(self, batch: EventWindows, x: torch.Tensor, y: torch.Tensor, weights: torch.Tensor
                  ) -> torch.Tensor:
        """The cross-fitted data term (B,) (class docstring), summed over references, of events warped to ``x, y``
        (R, N) [px] with their weights ``weights`` (R, N): per reference, pixel and polarity the mean over
        ordered pairs of different folds of the folds' average timestamps' product, ``((sum_k A^k)^2 - sum_k
        (A^k)^2) / (F (F - 1))``, summed over the pixels where at least two folds vote in one polarity, over
        their number."""
        B, H, W, b = batch.count, batch.height, batch.width, batch.window
        R = x.shape[0]
        folds = self.cross_fit.folds
        fold = self.cross_fit.fold(batch)
        keep = torch.ones_like(x)
        if self.purge:
            keep = _inside(batch, x.detach(), y.detach()).all(0).to(x.dtype).expand_as(x)
        on = (batch.polarity > 0).long()
        own = (on * folds + fold) * B + b                                        # (N,): polarity, fold, window
        image = (torch.arange(R, device=x.device)[:, None] * (2 * folds * B) + own[None]).reshape(-1)
        count = 2 * R * folds * B
        counts = accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), keep.reshape(-1), image, count, H, W)
        stamps = accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), (keep * weights).reshape(-1), image,
                                             count, H, W)
        counts, stamps = counts.reshape(R, 2, folds, B, H * W), stamps.reshape(R, 2, folds, B, H * W)
        average = stamps / (counts + self.eps)                                   # (refs, polarity, fold, B, HW)
        pairs = (average.sum(2) ** 2 - (average * average).sum(2)) / (folds * (folds - 1))
        square = pairs.sum((1, 3))                                               # (refs, B)
        voting = ((counts.detach() > 0).sum(2) >= 2).any(1)                     # (refs, B, HW): 2 folds, 1 polarity
        return (square / voting.sum(-1).clamp(min=1).to(square.dtype)).sum(0)


def _sample_indexed(images: torch.Tensor, image: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bilinear value (N,) of ``images`` (M, H, W) at points ``x, y`` (N,), point k read from ``images[image[k]]``
    (zero outside; :func:`cmax.iwe.sample_bilinear` with one image per point)."""
    M, H, W = images.shape
    Hp, Wp = H + 2, W + 2
    canvas = torch.nn.functional.pad(images, (1, 1, 1, 1)).reshape(-1)
    x0, y0 = torch.floor(x.detach()), torch.floor(y.detach())
    fx, fy = x - x0, y - y0
    valid = ((x0 >= -1) & (x0 <= W - 1) & (y0 >= -1) & (y0 <= H - 1)).to(images.dtype)
    x0, y0 = _finite_corner(x0), _finite_corner(y0)
    corner = image * (Hp * Wp) + (y0.clamp(-1, H - 1).long() + 1) * Wp + x0.clamp(-1, W - 1).long() + 1
    value = ((1 - fx) * (1 - fy) * canvas[corner] + fx * (1 - fy) * canvas[corner + 1]
             + (1 - fx) * fy * canvas[corner + Wp] + fx * fy * canvas[corner + Wp + 1])
    return value * valid


def _own_image_values(batch: EventWindows, x: torch.Tensor, y: torch.Tensor, sigma: float) -> torch.Tensor:
    """Each event's value (N,) in the blurred (``sigma`` px) image of the events of its window and polarity at
    pixels ``x, y`` (N,), read at its own pixel (the adjoint of its vote: its share of the energy ``sum I^2``)."""
    image = (batch.polarity > 0).long() * batch.count + batch.window
    images = blur(accumulate_bilinear_indexed(x, y, None, image, 2 * batch.count, batch.height, batch.width), sigma)
    return _sample_indexed(images, image, x, y)


class HeldOutSplit(str, enum.Enum):
    """How :class:`CrossFit` keeps an event out of the image it is read in: ``random``, events dealt at random
    (seeded, by their place in their window) into ``folds`` folds; ``pixels``, by their own pixel, squares of
    ``block`` x ``block`` px dealt in a checkerboard (``(col // block + row // block) % folds``), so that the
    events of one pixel, which share its depth, never read each other; ``leave_one_out``, each event's own
    kernel subtracted from the image it is read in (the exact self term of the blurred bilinear vote)."""

    RANDOM = "random"
    PIXELS = "pixels"
    LEAVE_ONE_OUT = "leave_one_out"


@dataclass(frozen=True)
class CrossFit:
    """Cross-fitting of a read-at-event objective (:class:`SweepVote`, :class:`PlaneVote`): each event is read
    in the image of the warped events of the *other* folds only (scaled by ``folds / (folds - 1)``, so that the
    image keeps its expected size), never in an image its own vote is part of.

    The image of warped events is a kernel density estimate of the warped events; an objective that reads each
    event in it rewards each event's density at itself, which the event's own kernel (and those of the events
    that share its parameters) inflate: the classic overfitting that leave-one-out likelihood cross-validation
    cures in bandwidth selection (Rudemo, "Empirical choice of histograms and kernel density estimators",
    Scand. J. Statist. 1982; Bowman, "An alternative method of cross-validation for the smoothing of density
    estimates", Biometrika 1984). Sample splitting with the roles swapped and the scores summed is the
    cross-fitting of Chernozhukov et al., "Double/debiased machine learning for treatment and structural
    parameters", Econometrics Journal 2018.

    Attributes
    ----------
    split : HeldOutSplit or str
        ``random``, ``pixels`` or ``leave_one_out`` (see :class:`HeldOutSplit`).
    folds : int
        Number of folds (>= 2; unused by ``leave_one_out``).
    seed : int
        Seed of the ``random`` deal (the same window gets the same folds alone or in a batch).
    block : int
        Side of the ``pixels`` split's squares [px].
    """

    split: HeldOutSplit | str = HeldOutSplit.RANDOM
    folds: int = 2
    seed: int = 0
    block: int = 1

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "split", HeldOutSplit(self.split))
        except ValueError:
            raise ValueError(f"CrossFit: split must be one of {[s.value for s in HeldOutSplit]}, got "
                             f"{self.split!r}") from None
        _require_int("CrossFit", "folds", self.folds, 2)
        _require_int("CrossFit", "seed", self.seed, 0)
        _require_int("CrossFit", "block", self.block, 1)

    def fold(self, batch: EventWindows) -> torch.Tensor | None:
        """The fold (N,) int64 of each event of ``batch`` (None for ``leave_one_out``)."""
        if self.split is HeldOutSplit.LEAVE_ONE_OUT:
            return None
        if self.split is HeldOutSplit.PIXELS:
            col = torch.floor(batch.x.detach() / self.block).long()
            row = torch.floor(batch.y.detach() / self.block).long()
            return torch.remainder(col + row, self.folds)
        counts = torch.zeros(batch.count, dtype=torch.long, device=batch.device).index_add_(
            0, batch.window, torch.ones_like(batch.window))                   # bincount, also on the meta device
        first = torch.cumsum(counts, 0) - counts
        order = torch.argsort(batch.window, stable=True)
        place = torch.empty_like(order)
        place[order] = torch.arange(len(batch), device=batch.device) - first[batch.window[order]]
        generator = torch.Generator().manual_seed(self.seed)
        deal = torch.randint(self.folds, (max(len(batch), 1),), generator=generator)   # a window's deal: a prefix
        return deal.to(batch.device)[place]


def _self_term(x: torch.Tensor, y: torch.Tensor, sigma: float, height: int, width: int) -> torch.Tensor:
    """What a point's own bilinear vote adds to the blurred (``sigma`` px) image read bilinearly at the point
    itself (N,): ``sum over corner pairs w_c w_c' g(c - c')`` (separable: one factor per axis), over the corners
    inside the ``height`` x ``width`` image (those the splat keeps)."""
    if sigma > 0:
        radius = max(1, math.ceil(3 * sigma))
        kernel = torch.exp(-torch.arange(0, 2, dtype=x.dtype, device=x.device) ** 2 / (2.0 * sigma * sigma))
        norm = 1.0 + 2.0 * sum(math.exp(-k * k / (2.0 * sigma * sigma)) for k in range(1, radius + 1))
        k0, k1 = kernel[0] / norm, kernel[1] / norm
    else:
        k0, k1 = 1.0, 0.0

    def axis(u: torch.Tensor, size: int) -> torch.Tensor:
        u0 = torch.floor(u.detach())
        f = u - u0
        m0 = ((u0 >= 0) & (u0 <= size - 1)).to(u.dtype)
        m1 = ((u0 + 1 >= 0) & (u0 + 1 <= size - 1)).to(u.dtype)
        return (m0 * (1 - f) ** 2 + m1 * f * f) * k0 + 2.0 * m0 * m1 * f * (1 - f) * k1

    return axis(x, width) * axis(y, height)


#: A cross-fitted event's normaliser is at least this fraction of its window's median (an event far from every
#: other fold's events has a largest held-out value near 0, and its vote divided by it would dominate the window).
HELD_OUT_FLOOR = 0.1


def _floored(batch: EventWindows, peak: torch.Tensor) -> torch.Tensor:
    """Each event's normaliser ``peak`` (N,), at least :data:`HELD_OUT_FLOOR` times its window's median
    (differentiable in ``peak``, the floor too)."""
    by_peak = torch.argsort(peak, stable=True)
    order = by_peak[torch.argsort(batch.window[by_peak], stable=True)]      # by window, then by peak
    counts = torch.zeros(batch.count, dtype=torch.long, device=peak.device).index_add_(
        0, batch.window, torch.ones_like(batch.window))
    lower = torch.cumsum(counts, 0) - counts + (counts - 1).clamp(min=0) // 2  # torch.median's (lower) middle
    median = torch.where(counts > 0, peak[order][lower.clamp(max=max(peak.numel() - 1, 0))], peak.new_zeros(()))
    floor = (HELD_OUT_FLOOR * median).clamp(min=1e-12)[batch.window]
    return torch.maximum(peak, floor)


def _held_out_values(x: torch.Tensor, y: torch.Tensor, image: torch.Tensor, count: int, height: int, width: int,
                     sigma: float, cross_fit: CrossFit | None, fold: torch.Tensor | None) -> torch.Tensor:
    """Value (M,) of each point ``x, y`` (M,) [px] in the blurred (``sigma`` px) image ``image[k]`` (of
    ``count``) of all points' bilinear votes; with ``cross_fit``, of the votes of the points of the other folds
    only (``fold`` (M,), scaled by ``folds / (folds - 1)``), or less the point's own vote (``leave_one_out``)."""
    if cross_fit is None or cross_fit.split is HeldOutSplit.LEAVE_ONE_OUT:
        images = blur(accumulate_bilinear_indexed(x, y, None, image, count, height, width), sigma)
        value = _sample_indexed(images, image, x, y)
        return value if cross_fit is None else value - _self_term(x, y, sigma, height, width)
    folds = cross_fit.folds
    index = fold * count + image
    images = accumulate_bilinear_indexed(x, y, None, index, folds * count, height, width).view(folds, count,
                                                                                               height, width)
    others = blur((images.sum(0, keepdim=True) - images).reshape(folds * count, height, width), sigma)
    return _sample_indexed(others, index, x, y) * (folds / (folds - 1))


@dataclass(frozen=True, eq=False)
class SweepVote:
    """The depth sweep's per-event normalised vote (lower is better): differentiable in depth; in the twist, with
    the normaliser held (below), so its twist gradient is not the objective's (finite differences of the twist
    move the normaliser too). Fix the normaliser for one twist with :meth:`with_motion` (the gradient is then
    exact), or optimise a motion with :class:`PlaneVote`, whose normaliser carries a gradient.

    Each event is warped to the window's ``reference`` time with its inverse
    depth; the blurred image of the warped events of its polarity is read back at
    its own warped position (the adjoint of the voting: event i's share of the
    energy ``sum I^2``), divided by the largest value the event reaches over a
    sweep of ``candidates`` constant inverse depths in ``rho_range`` (computed
    without gradient: one vote per event; an event that some candidate pushes out
    of the image is divided by the window's median largest value instead), and
    averaged over the events that stay inside. This is the cost of the plane
    sweep (Rebecq, Gallego, Mueggler, Scaramuzza, "EMVS: Event-based multi-view
    stereo", IJCV 2018; the contrast of Gallego, Rebecq, Scaramuzza, "A unifying
    contrast maximization framework for event cameras", CVPR 2018) with the
    per-event depth free; the result is ``-mean vote``.

    Attributes
    ----------
    rho_range : (float, float)
        Inverse depths [1/m] of the normalising sweep.
    candidates : int
        Constant inverse depths swept for the normaliser.
    sigma : float
        Blur [px].
    reference : float
        Reference time as a fraction of the window.
    scale : Tensor (N,) or None
        A fixed normaliser (:meth:`with_motion`); None: swept at every call.
    cross_fit : CrossFit or None
        Read each event in the image of the other folds' events only (the normaliser's sweep too); None: in
        the image of all events, its own vote included.
    """

    rho_range: tuple[float, float] = (1.0 / 60.0, 2.0)
    candidates: int = 12
    sigma: float = 1.0
    reference: float = 0.5
    scale: torch.Tensor | None = None
    cross_fit: CrossFit | None = None

    def __post_init__(self) -> None:
        if not (0 <= self.rho_range[0] < self.rho_range[1] < math.inf):
            raise ValueError(f"rho_range must be increasing, finite and >= 0 [1/m], got {self.rho_range}")
        _require_int("SweepVote", "candidates", self.candidates, 2)
        _require_number("SweepVote", "sigma", self.sigma, 0.0)
        _require_number("SweepVote", "reference", self.reference)
        _require_cross_fit("SweepVote", self.cross_fit)

    def _scores(self, batch: EventWindows, params: DepthMotion, dt: torch.Tensor, rays: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor]:
        x, y = warp_windows(batch, params, dt, rays)
        x, y = x[0], y[0]
        if self.cross_fit is None:
            return _own_image_values(batch, x, y, self.sigma), _inside(batch, x.detach(), y.detach())
        image = (batch.polarity > 0).long() * batch.count + batch.window
        values = _held_out_values(x, y, image, 2 * batch.count, batch.height, batch.width, self.sigma,
                                  self.cross_fit, self.cross_fit.fold(batch))
        return values, _inside(batch, x.detach(), y.detach())

    def _dt(self, batch: EventWindows) -> torch.Tensor:
        return (batch.t - self.reference * batch.duration_s.to(batch.dtype)[batch.window])[None]

    def normaliser(self, batch: EventWindows, twist: torch.Tensor) -> torch.Tensor:
        """What each event of ``batch`` has its vote divided by (N,): its largest value over the constant-depth sweep
        with the windows' ``twist`` (B, 6), or the window's median largest value for an event some candidate
        pushes out of the image. No gradient."""
        B, rays, dt = batch.count, batch.rays(), self._dt(batch)
        with torch.no_grad():
            peaks, always = [], torch.ones(len(batch), dtype=torch.bool, device=batch.device)
            for rho in torch.linspace(*self.rho_range, self.candidates, dtype=batch.dtype).tolist():
                candidate = DepthMotion(torch.full((B, 1, 1, 1), rho, dtype=batch.dtype, device=batch.device),
                                        twist.detach())
                score, inside = self._scores(batch, candidate, dt, rays)
                peaks.append(score * inside)
                always &= inside
            peak = torch.stack(peaks).max(0).values
            typical = torch.stack([peak[always & (batch.window == k)].median()
                                   if bool((always & (batch.window == k)).any()) else peak.median()
                                   for k in range(B)])
            scale = torch.where(always, peak, typical[batch.window])
            return scale.clamp(min=1e-12) if self.cross_fit is None else _floored(batch, scale)

    def with_motion(self, batch: EventWindows, twist: torch.Tensor) -> "SweepVote":
        """This objective with the normaliser of a known ``twist`` (B, 6) fixed (:meth:`normaliser`): for a
        depth-only optimisation of ``batch`` with that twist it gives the same values, without re-sweeping
        at every call."""
        return dataclasses.replace(self, scale=self.normaliser(batch, twist))

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        if self.scale is not None and self.scale.shape != (len(batch),):
            raise ValueError(f"scale holds {self.scale.shape[0]} events, the batch {len(batch)}")
        scale = self.normaliser(batch, params.twist) if self.scale is None else self.scale
        score, inside = self._scores(batch, params, self._dt(batch), batch.rays())
        inside = inside.to(score.dtype)
        votes, kept = batch.window_sum(inside * score / scale), batch.window_sum(inside)
        return -votes / kept.clamp(min=1.0)


class PlaneValues(NamedTuple):
    """What :class:`PlaneVote` reads for one motion: each event's value on each plane (C, N), whether it stays
    inside the image on every plane (N,) (1.0 / 0.0), and what its value is divided by (N,)."""

    values: torch.Tensor
    kept: torch.Tensor
    scale: torch.Tensor


class VoteNormaliser(str, enum.Enum):
    """What :class:`PlaneVote` divides each event's value by: ``event_peak``, the event's largest value over
    the planes (one vote per event, as the sweep's :func:`cmax.contrast.sweep.vote_scale`); ``window``, the
    mean over the window's events of the unwarped image's value at them (one number per window that no
    motion changes, so that a sharper motion scores higher)."""

    EVENT_PEAK = "event_peak"
    WINDOW = "window"


@dataclass(frozen=True, eq=False)
class PlaneVote:
    """Each event read in the image of all events warped with one constant inverse depth, at its own
    (lower is better).

    For ``planes`` inverse depths log-spaced over ``rho_range`` every event of a window is warped to the
    ``reference`` time with that one inverse depth and imaged per polarity (blur ``sigma``); event i's
    value on plane c is that image read back at its own warped position (a slice of the space sweep's
    volume: the disparity space image of Rebecq, Gallego, Mueggler, Scaramuzza, "EMVS: Event-based
    multi-view stereo", IJCV 2018, read per event as the sweep's vote). The objective reads each event on
    the planes at its own inverse depth (the map at its pixel, :func:`event_inverse_depth`), linearly
    between the two nearest planes in log inverse depth, divides by the :class:`VoteNormaliser`, and
    averages over the events that stay inside the image on every plane: ``-mean vote``, plus
    ``smoothness`` times :func:`log_depth_variation`.

    Unlike :class:`SweepVote`, whose events are read in the image of the *current* depth map (which a free
    depth can focus onto itself), the planes' images do not depend on the depth map: nothing collapses, and
    a node's best depth is the peak of its events' columns, the sweep's own choice. The planes' values
    depend on the motion: :meth:`with_motion` computes them once for a known twist (a depth-only
    optimisation); without it they are computed at every call, differentiable in the twist.

    Attributes
    ----------
    rho_range : (float, float)
        Smallest and largest inverse depth of the planes [1/m], ``0 < lo < hi``; depths beyond are read on
        the end planes (no gradient there).
    planes : int
        Number of planes.
    sigma : float
        Blur of the planes' images [px].
    reference : float
        Reference time as a fraction of the window.
    normaliser : VoteNormaliser or str
    smoothness : float
        Weight of :func:`log_depth_variation`.
    motion_weight : float
        Weight of a term that ranks motions and does not depend on the depth map (0: none): minus the
        sweep's best focus per cell, ``sum over cells of max over planes of the cell's summed votes``,
        each vote divided by the ``window`` normaliser (which keeps a sharper motion's contrast), over the
        window's kept events. It is the plane sweep's cost with each cell's depth profiled out (Rebecq et
        al. 2018, per cell as the fit's patch-wise motion objective), so a depth-only descent sees the
        event-peak depth term alone while a motion that focuses no cell scores worse.
    motion_cells : (int, int)
        Rows and columns of those cells, over each window's image.
    values : PlaneValues or None
        The planes' values, which events stay inside and the normaliser, fixed by :meth:`with_motion`
        (None: computed at each call).
    motion_term : Tensor (B,) or None
        The motion term of those fixed values (:meth:`motion_profile`), fixed with them when
        ``motion_weight`` is not 0: with the motion known it is a constant of the depth map.
    cross_fit : CrossFit or None
        Read each event in the planes' images of the other folds' events only; None: of all events, its own
        vote included.
    """

    rho_range: tuple[float, float] = (1.0 / 60.0, 2.0)
    planes: int = 32
    sigma: float = 1.0
    reference: float = 0.5
    normaliser: VoteNormaliser | str = VoteNormaliser.EVENT_PEAK
    smoothness: float = 0.0
    motion_weight: float = 0.0
    motion_cells: tuple[int, int] = (6, 8)
    values: PlaneValues | None = None
    motion_term: torch.Tensor | None = None
    cross_fit: CrossFit | None = None

    def __post_init__(self) -> None:
        lo, hi = self.rho_range
        if not (0 < lo < hi):
            raise ValueError(f"rho_range must be increasing and > 0 [1/m] (the planes are log-spaced), got "
                             f"{self.rho_range}")
        _require_int("PlaneVote", "planes", self.planes, 2)
        _require_number("PlaneVote", "smoothness", self.smoothness, 0.0)
        _require_number("PlaneVote", "sigma", self.sigma, 0.0)
        _require_number("PlaneVote", "reference", self.reference)
        _require_cross_fit("PlaneVote", self.cross_fit)
        if not (isinstance(self.motion_weight, (int, float)) and math.isfinite(self.motion_weight)
                and self.motion_weight >= 0):
            raise ValueError(f"motion_weight must be a finite number >= 0, got {self.motion_weight!r}")
        if not (len(self.motion_cells) == 2 and all(isinstance(n, int) and n >= 1 for n in self.motion_cells)):
            raise ValueError(f"motion_cells must be two positive integers (rows, cols), got {self.motion_cells!r}")
        try:
            object.__setattr__(self, "normaliser", VoteNormaliser(self.normaliser))
        except ValueError:
            raise ValueError(f"normaliser must be one of {[n.value for n in VoteNormaliser]}, got "
                             f"{self.normaliser!r}") from None

    def plane_inverse_depths(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """The planes' inverse depths (C,) [1/m] of ``dtype``, log-spaced over ``rho_range``."""
        lo, hi = self.rho_range
        return torch.exp(torch.linspace(math.log(lo), math.log(hi), self.planes, dtype=dtype))

    def plane_values(self, batch: EventWindows, twist: torch.Tensor) -> PlaneValues:
        """:class:`PlaneValues` of the windows of ``batch`` at their ``twist`` (B, 6): the planes' values are
        differentiable in it.

        All planes at once: the depth-free parts of the warp (:func:`cmax.warp.se3_parts`) once, every plane's
        points as ``rotated + rho_c moved`` (C, N), one splat into the ``C x 2B`` images (plane, polarity,
        window), one blur, one read-back."""
        B, C, dtype, b = batch.count, self.planes, batch.dtype, batch.window
        dt = batch.t - self.reference * batch.duration_s.to(dtype)[b]
        twists = twist_at_speed(twist.to(dtype), batch.speed)[b]                  # (N, 6)
        rotated, moved = se3_parts(batch.rays(), dt, twists[:, :3], twists[:, 3:])
        rho = self.plane_inverse_depths(dtype).to(rotated.device)
        points = rotated[None] + rho[:, None, None] * moved[None]                  # (C, N, 3)
        identity = torch.eye(3, dtype=dtype, device=points.device)
        xn, yn = project(points, identity)
        K = batch.K.to(dtype)[b]
        x, y = K[:, 0, 0] * xn + K[:, 0, 1] * yn + K[:, 0, 2], K[:, 1, 1] * yn + K[:, 1, 2]
        own = (batch.polarity > 0).long() * B + b                                  # (N,): polarity, window
        image = (torch.arange(C, device=x.device)[:, None] * (2 * B) + own[None]).reshape(-1)
        xs, ys = x.reshape(-1), y.reshape(-1)
        fold = None if self.cross_fit is None else self.cross_fit.fold(batch)
        values = _held_out_values(xs, ys, image, C * 2 * B, batch.height, batch.width, self.sigma, self.cross_fit,
                                  None if fold is None else fold.repeat(C)).view(C, len(batch))
        kept = _inside(batch, x.detach(), y.detach()).all(0).to(values.dtype)
        return PlaneValues(values, kept, self._scale(batch, values, kept))

    def with_motion(self, batch: EventWindows, twist: torch.Tensor) -> "PlaneVote":
        """This objective with the :class:`PlaneValues` of a known ``twist`` (B, 6) fixed: for a depth-only
        optimisation of ``batch`` with that twist it gives the same values, without re-imaging the planes."""
        with torch.no_grad():
            values = self.plane_values(batch, twist.detach())
            term = self.motion_profile(batch, values.values, values.kept) if self.motion_weight else None
            return dataclasses.replace(self, values=values, motion_term=term)

    def _scale(self, batch: EventWindows, values: torch.Tensor, kept: torch.Tensor) -> torch.Tensor:
        """What each event's value is divided by (N,): see :class:`VoteNormaliser`."""
        if self.normaliser is VoteNormaliser.EVENT_PEAK:
            peak = values.max(0).values
            return peak.clamp(min=1e-12) if self.cross_fit is None else _floored(batch, peak)
        return self._window_scale(batch, values, kept)

    def _window_scale(self, batch: EventWindows, values: torch.Tensor, kept: torch.Tensor) -> torch.Tensor:
        """The ``window`` normaliser of each event (N,): its window's mean unwarped image value at its events."""
        with torch.no_grad():
            x, y = batch.x.to(values.dtype), batch.y.to(values.dtype)
            unwarped = _own_image_values(batch, x, y, self.sigma) * kept
            total, count = batch.window_sum(unwarped), batch.window_sum(kept)
            return (total / count.clamp(min=1.0)).clamp(min=1e-12)[batch.window]

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        values, kept, scale = self.plane_values(batch, params.twist) if self.values is None else self.values
        if values.shape != (self.planes, len(batch)):
            raise ValueError(f"the fixed plane values hold {values.shape[1]} events, the batch {len(batch)}")
        dtype = values.dtype
        lo, hi = (math.log(r) for r in self.rho_range)
        rho = event_inverse_depth(batch, params.inverse_depth.to(dtype)).clamp(min=1e-12)
        position = ((torch.log(rho) - lo) / (hi - lo) * (self.planes - 1)).clamp(0, self.planes - 1)
        below = torch.floor(position.detach()).long().clamp(max=self.planes - 2)
        fraction = position - below
        events = torch.arange(values.shape[1], device=values.device)
        value = (1 - fraction) * values[below, events] + fraction * values[below + 1, events]
        vote = kept * value / scale
        votes, count = batch.window_sum(vote), batch.window_sum(kept)
        loss = -votes / count.clamp(min=1.0)
        if self.motion_weight:
            fixed = self.values is not None and self.motion_term is not None
            term = self.motion_term if fixed else self.motion_profile(batch, values, kept)
            loss = loss + self.motion_weight * term
        return _plus_smoothness(loss, self.smoothness, batch, params)

    def motion_profile(self, batch: EventWindows, values: torch.Tensor, kept: torch.Tensor) -> torch.Tensor:
        """The depth-free motion term (B,) of ``motion_weight`` (see the class docstring) of the windows of ``batch``,
        from the planes' ``values`` (C, N) and ``kept`` (N,) of one motion; differentiable in the values."""
        B, (rows, cols) = batch.count, self.motion_cells
        scale = self._window_scale(batch, values, kept)
        with torch.no_grad():
            row = (batch.y * rows / batch.height).long().clamp(0, rows - 1)
            col = (batch.x * cols / batch.width).long().clamp(0, cols - 1)
            cell = (batch.window * rows + row) * cols + col
            count = batch.window_sum(kept)
        per_cell = torch.zeros(values.shape[0], B * rows * cols, dtype=values.dtype, device=batch.device).index_add(
            1, cell, kept * values / scale)                                  # (C, cells): each plane's summed votes
        best = per_cell.max(0).values.view(B, rows * cols).sum(1)
        return -best / count.clamp(min=1.0)


@dataclass(frozen=True)
class LocalContrast:
    """Contrast of each cell's own events in a small image around its cell, plus smoothness (lower is better).

    The events are split by their pixel into ``cells``; each cell's events, warped to
    the ``reference`` time, vote into an image of the cell plus ``margin`` px on each
    side (one per polarity), and the cell's contrast is ``sum I^2`` of its blurred
    images divided by the same for its unwarped events (no gradient). A cell
    cannot raise it by piling its events onto another cell's edges. The loss is
    ``-mean over cells with events`` plus ``smoothness`` times the total variation
    of the log inverse depth. The per-patch (local) contrast follows Stoffregen &
    Kleeman, "Event cameras, contrast maximization and reward functions: an
    analysis", CVPR 2019, and the patch-wise motion of Shiba, Aoki, Gallego,
    "Secrets of event-based optical flow", ECCV 2022 (which also regularises with
    total variation).

    Attributes
    ----------
    cells : (int, int)
        Rows and columns of cells.
    margin : int
        Extra pixels around each cell's image.
    sigma : float
        Blur [px].
    reference : float
        Reference time as a fraction of the window.
    smoothness : float
        Weight of :func:`log_depth_variation` (0: none).
    """

    cells: tuple[int, int] = (6, 8)
    margin: int = 8
    sigma: float = 1.0
    reference: float = 0.5
    smoothness: float = 0.0

    def __post_init__(self) -> None:
        _require_grid("LocalContrast", "cells", self.cells, 1)
        _require_int("LocalContrast", "margin", self.margin, 0)
        _require_number("LocalContrast", "smoothness", self.smoothness, 0.0)
        _require_number("LocalContrast", "sigma", self.sigma, 0.0)
        _require_number("LocalContrast", "reference", self.reference)

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        B, H, W = batch.count, batch.height, batch.width
        gh, gw = self.cells
        ch, cw = -(-H // gh), -(-W // gw)
        row = (batch.y.detach() / ch).long().clamp(0, gh - 1)
        col = (batch.x.detach() / cw).long().clamp(0, gw - 1)
        cell = row * gw + col
        C = gh * gw
        image = ((batch.polarity > 0).long() * B + batch.window) * C + cell             # (N,)
        corner = torch.arange(2 * B * C, device=batch.device) % C                          # each image's cell
        origins = torch.stack([(corner % gw) * cw, (corner // gw) * ch], -1).to(batch.dtype) - self.margin
        size = (ch + 2 * self.margin, cw + 2 * self.margin)

        def energy(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
            images = local_contrast(x, y, image, origins, count=2 * B * C, patch=size, sigma=self.sigma)
            return images.view(2, B, C).sum(0)                                          # (B, C)

        with torch.no_grad():
            baseline = energy(batch.x, batch.y)
        dt = (batch.t - self.reference * batch.duration_s.to(batch.dtype)[batch.window])[None]
        x, y = warp_windows(batch, params, dt)
        ratio = torch.where(baseline > 0, energy(x[0], y[0]) / baseline.clamp(min=1e-12), 0.0)
        used = (baseline > 0).sum(1).clamp(min=1).to(ratio.dtype)
        loss = -ratio.sum(1) / used
        return _plus_smoothness(loss, self.smoothness, batch, params)


@dataclass(frozen=True)
class GlobalContrast:
    """Normalised multi-reference contrast of the whole image (lower is better): ``-C(warped) / C(unwarped)``.

    ``C`` is the mean over reference times (fractions ``references`` of the
    window) of the contrast (``kind``: variance, paper eq. 11, or gradient
    magnitude) of the blurred image of warped events; dividing by the unwarped
    events' value makes it dimensionless (about -1 without motion). Gallego,
    Rebecq, Scaramuzza, "A unifying contrast maximization framework for event
    cameras", CVPR 2018; the multiple references against event collapse: Shiba,
    Aoki, Gallego, "Event collapse in contrast maximization frameworks", Sensors
    2022. A free depth can collapse it below the truth's value (see
    ``docs/contrast_objective.md``): use it for motion, not for depth.

    Attributes
    ----------
    references : tuple of float
        Reference times as fractions of each window.
    sigma : float
        Blur [px].
    kind : {"variance", "gradient"}
    """

    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    kind: str = "variance"

    def __post_init__(self) -> None:
        contrast_of_images(torch.zeros(1, 1, 1), self.kind)      # validates the name
        if not self.references:
            raise ValueError("references: need at least one reference time")
        for reference in self.references:
            _require_number("GlobalContrast", "references", reference)
        _require_number("GlobalContrast", "sigma", self.sigma, 0.0)

    def _per_window(self, batch: EventWindows, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        R, B = x.shape[0], batch.count
        image = (torch.arange(R, device=x.device)[:, None] * B + batch.window[None, :]).reshape(-1)
        images = blur(accumulate_bilinear_indexed(x.reshape(-1), y.reshape(-1), None, image, R * B, batch.height,
                                                  batch.width), self.sigma)
        return contrast_of_images(images, self.kind).view(R, B).mean(0)

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        fractions = torch.tensor(self.references, dtype=torch.float64, device=batch.device)
        refs = (fractions[:, None] * batch.duration_s.to(torch.float64)[None, :]).to(batch.dtype)   # (R, B)
        x, y = warp_windows(batch, params, batch.t[None, :] - refs[:, batch.window])
        with torch.no_grad():
            baseline = self._per_window(batch, batch.x[None], batch.y[None])
        contrast = self._per_window(batch, x, y)
        return -torch.where(baseline > 0, contrast / torch.where(baseline > 0, baseline, 1.0), 0.0)


@dataclass(frozen=True)
class CollapseGuard:
    """Shiba et al.'s guard against event collapse: the mean squared log area change of the warp (B,).

    Measured on a ``lattice`` of probe pixels of each window warped by time offsets
    ``times`` (in units of the window's duration) with the inverse depth at the probes: 0 for a rigid
    image motion, large when the warp squeezes the image (:func:`cmax.objectives.deformation`).
    Shiba, Aoki, Gallego, "Event collapse in contrast maximization frameworks",
    Sensors 2022, doi:10.3390/s22145190.

    Attributes
    ----------
    lattice : (int, int)
        Rows and columns of probes, spread over 10-90 % of the image.
    times : tuple of float
        Time offsets of the probes' warps, in units of the window's duration (``PROBE_TIMES``, as
        ``FitSettings.collapse_times``).
    """

    lattice: tuple[int, int] = (9, 12)
    times: tuple[float, ...] = PROBE_TIMES

    def __post_init__(self) -> None:
        _require_grid("CollapseGuard", "lattice", self.lattice, 2)   # one row or column of probes holds no cell
        if not self.times:
            raise ValueError("times: need at least one probe time")
        for time in self.times:
            _require_number("CollapseGuard", "times", time)

    @_non_finite_scores_nan
    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        B, H, W, dtype, device = batch.count, batch.height, batch.width, batch.dtype, batch.device
        twist = twist_at_speed(params.twist.to(dtype), batch.speed)
        rows, cols = self.lattice
        ys, xs = torch.meshgrid(torch.linspace(0.1, 0.9, rows, dtype=dtype, device=device) * H,
                                torch.linspace(0.1, 0.9, cols, dtype=dtype, device=device) * W, indexing="ij")
        P = xs.numel()
        probes = EventWindows(xs.reshape(-1).repeat(B), ys.reshape(-1).repeat(B),
                              torch.zeros(B * P, dtype=dtype, device=device),
                              torch.ones(B * P, dtype=dtype, device=device),
                              torch.arange(B, device=device).repeat_interleave(P), batch.K.to(dtype),
                              batch.duration_s.to(dtype), W, H)
        times = torch.tensor(self.times, dtype=dtype, device=device)[:, None] * probes.duration_s[probes.window][None]
        x1, y1 = warp_windows(probes, DepthMotion(params.inverse_depth, twist), times)
        x1, y1 = x1.view(len(self.times), B, rows, cols), y1.view(len(self.times), B, rows, cols)
        return torch.stack([deformation(xs, ys, x1[:, k], y1[:, k]) for k in range(B)])


@dataclass(frozen=True)
class WeightedSum:
    """``sum_k weight_k * objective_k(batch, params)`` (B,): e.g. a contrast plus the collapse guard.

    Attributes
    ----------
    terms : tuple of (float, objective)
    """

    terms: tuple[tuple[float, object], ...]

    def __post_init__(self) -> None:
        if not self.terms or not all(len(t) == 2 and callable(t[1]) for t in self.terms):
            raise ValueError("terms must be a non-empty tuple of (weight, objective) pairs")

    def __call__(self, batch: EventWindows, params: DepthMotion) -> torch.Tensor:
        return sum(float(w) * objective(batch, params) for w, objective in self.terms if w != 0)


#: The depth-and-motion objective shared by the fit's refinement and :mod:`learned` (docs/contrast_objective.md).
SHARED_OBJECTIVE = AverageTimestamp(smoothness=0.003)
