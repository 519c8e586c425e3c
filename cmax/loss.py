"""Deprecated: the contrast objectives live in :mod:`cmax.contrast`; this module adapts the old names to them.

``contrast_loss(events, rho, twist, K)`` is
``WeightedSum(((1, GlobalContrast(...)), (collapse_weight, CollapseGuard())))`` of
:mod:`cmax.contrast.objectives` on an :class:`cmax.contrast.EventWindows`; the
network trains on :data:`cmax.contrast.SHARED_OBJECTIVE` instead (see
``docs/contrast_objective.md``). Kept importable for old scripts; use
:mod:`cmax.contrast` in new code.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Sequence

import torch

from cmax.contrast.batch import EventWindows
from cmax.contrast.objectives import CollapseGuard, DepthMotion, GlobalContrast, WeightedSum
from cmax.warp import WarpEvents

__all__ = ["EventBatch", "ContrastLoss", "contrast_loss", "contrast_loss_terms"]

warnings.warn("cmax.loss is deprecated: use cmax.contrast (EventWindows, GlobalContrast, CollapseGuard, "
              "SHARED_OBJECTIVE)", DeprecationWarning, stacklevel=2)


@dataclass(frozen=True, eq=False)
class EventBatch:
    """Deprecated: :class:`cmax.contrast.EventWindows` without the intrinsics (given to :func:`contrast_loss`)."""

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
    def _of(cls, w: EventWindows) -> "EventBatch":
        return cls(w.x, w.y, w.t, w.polarity, w.window, w.duration_s, w.count, w.width, w.height)

    @classmethod
    def from_windows(cls, windows: Sequence[WarpEvents]) -> "EventBatch":
        """:meth:`cmax.contrast.EventWindows.from_warp_events`."""
        return cls._of(EventWindows.from_warp_events(windows))

    @classmethod
    def from_padded(cls, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor, polarity: torch.Tensor,
                    valid: torch.Tensor, duration_s: torch.Tensor, *, width: int, height: int) -> "EventBatch":
        """:meth:`cmax.contrast.EventWindows.from_padded` (identity intrinsics until :meth:`windows`)."""
        K = torch.eye(3, dtype=x.dtype).expand(x.shape[0], 3, 3)
        return cls._of(EventWindows.from_padded(x, y, t, polarity, valid, duration_s, K, width=width, height=height))

    def windows(self, K: torch.Tensor) -> EventWindows:
        """The :class:`cmax.contrast.EventWindows` of these events with intrinsics ``K`` (B, 3, 3)."""
        if K.shape != (self.count, 3, 3):
            raise ValueError(f"K must have shape ({self.count}, 3, 3), got {tuple(K.shape)}")
        return EventWindows(self.x, self.y, self.t, self.polarity, self.batch_index, K.to(self.x.dtype),
                            self.duration_s, self.width, self.height)


@dataclass(frozen=True)
class ContrastLoss:
    """Deprecated settings of :func:`contrast_loss` (``cmax.contrast.GlobalContrast`` plus ``CollapseGuard``)."""

    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    kind: str = "variance"
    collapse_weight: float = 0.1

    def __call__(self, events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor,
                 K: torch.Tensor) -> torch.Tensor:
        return contrast_loss(events, inverse_depth, twist, K, references=self.references, sigma=self.sigma,
                             kind=self.kind, collapse_weight=self.collapse_weight)


def _windows_and_params(events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor
                        ) -> tuple[EventWindows, DepthMotion]:
    if not isinstance(events, EventBatch):
        raise TypeError(f"events must be a cmax.loss.EventBatch, got {type(events).__name__}")
    if K.shape != (events.count, 3, 3):
        raise ValueError(f"K must have shape ({events.count}, 3, 3), got {tuple(K.shape)}")
    dtype = events.x.dtype
    return events.windows(K), DepthMotion(inverse_depth.to(dtype), twist.to(dtype))


def contrast_loss_terms(events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor, *,
                        references: tuple[float, ...] = (0.0, 0.5, 1.0), sigma: float = 1.0,
                        kind: str = "variance", collapse_weight: float = 0.1) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised contrast (B,) and deformation (B,): ``-GlobalContrast`` and ``CollapseGuard`` (zeros if off)."""
    batch, params = _windows_and_params(events, inverse_depth, twist, K)
    normalised = -GlobalContrast(tuple(references), sigma, kind)(batch, params)
    guard = CollapseGuard()(batch, params) if collapse_weight > 0 else torch.zeros_like(normalised)
    return normalised, guard


def contrast_loss(events: EventBatch, inverse_depth: torch.Tensor, twist: torch.Tensor, K: torch.Tensor, *,
                  references: tuple[float, ...] = (0.0, 0.5, 1.0), sigma: float = 1.0, kind: str = "variance",
                  collapse_weight: float = 0.1, reduction: str = "mean") -> torch.Tensor:
    """``-contrast(warped) / contrast(unwarped) + collapse_weight * deformation``, mean (``()``) or per window (B,)."""
    if reduction not in ("mean", "none"):
        raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
    batch, params = _windows_and_params(events, inverse_depth, twist, K)
    objective = WeightedSum(((1.0, GlobalContrast(tuple(references), sigma, kind)),
                             (float(collapse_weight), CollapseGuard())))
    per_window = objective(batch, params)
    return per_window.mean() if reduction == "mean" else per_window
