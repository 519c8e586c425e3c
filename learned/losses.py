"""Training losses: scale-invariant and gradient-matching (teacher), contrast + distillation (student).

* ``L_si`` (Eigen et al., NeurIPS 2014): ``R = log d - log g`` on valid pixels,
  ``mean(R^2) - mean(R)^2``.
* ``L_grad`` (Li & Snavely, MegaDepth, CVPR 2018): at each scale ``s`` (the
  network's output scales, the ground truth average-pooled with its mask),
  ``mean(|Sobel_x R^s| + |Sobel_y R^s|)`` over pixels whose 3x3 neighbourhood is valid
  (kornia's Sobel).
* ``L_teacher = L_si + lambda L_grad``;
* ``L_student = L_contrast + (1 - lambda) L1(rho_teacher, rho_student)``, lambda = 0.6,
  with ``L_contrast`` the shared depth-and-motion objective of the contrast core,
  :data:`cmax.contrast.SHARED_OBJECTIVE` (the very object, imported), applied to the
  predicted inverse depth and twist (EvtSlowTV eqs. 12-15, with the objective of
  ``docs/contrast_objective.md`` in place of the IWE variance). Metric scale: the
  batch carries the known speed of each window (:attr:`cmax.contrast.EventWindows.speed`),
  the objective rescales the predicted ``v`` to it, so the contrast fixes the depth in
  metres; a window of unknown speed (NaN) leaves ``v`` as predicted and its scale to
  the teacher term.
"""
from __future__ import annotations

import kornia
import torch
from torch.nn import functional as F

from cmax.contrast import SHARED_OBJECTIVE, DepthMotion, EventWindows

__all__ = ["scale_invariant_loss", "gradient_matching_loss", "teacher_loss", "speed_loss", "student_loss", "LAMBDA"]

#: The paper's lambda.
LAMBDA = 0.6


def _check(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor) -> None:
    if pred.dim() != 4 or pred.shape[1] != 1 or pred.shape != gt.shape or gt.shape != mask.shape:
        raise ValueError(f"pred, gt and mask must share one shape (B, 1, H, W), got {tuple(pred.shape)}, "
                         f"{tuple(gt.shape)}, {tuple(mask.shape)}")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got {mask.dtype}")


def _log_residual(pred_depth: torch.Tensor, gt_depth: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    safe_gt = torch.where(mask, gt_depth, torch.ones_like(gt_depth))
    return torch.where(mask, torch.log(pred_depth) - torch.log(safe_gt), torch.zeros_like(pred_depth))


def scale_invariant_loss(pred_depth: torch.Tensor, gt_depth: torch.Tensor, mask: torch.Tensor, *,
                         variance_weight: float = 1.0) -> torch.Tensor:
    """``mean(R^2) - w mean(R)^2`` per image over its valid pixels, averaged over the batch.

    ``variance_weight`` w = 1 is the paper's fully scale-invariant form (eq. 13), which leaves
    the absolute scale free; w < 1 (Eigen et al. used 0.5) also penalises a global scale error.

    Parameters
    ----------
    pred_depth, gt_depth : Tensor (B, 1, H, W)
        Depths [m] (> 0 where ``mask``).
    mask : Tensor (B, 1, H, W) bool
        Valid ground truth. Images without valid pixels contribute 0.

    Returns
    -------
    Tensor, shape ()
    """
    _check(pred_depth, gt_depth, mask)
    R = _log_residual(pred_depth, gt_depth, mask).flatten(1)
    n = mask.flatten(1).sum(1).clamp(min=1).to(R.dtype)
    return (R.pow(2).sum(1) / n - variance_weight * (R.sum(1) / n).pow(2)).mean()


def gradient_matching_loss(pred_depths: tuple[torch.Tensor, ...] | list[torch.Tensor], gt_depth: torch.Tensor,
                           mask: torch.Tensor) -> torch.Tensor:
    """Multi-scale gradient matching of the log-depth residual (Sobel), summed over scales.

    ``pred_depths`` (B, 1, H_s, W_s) [m] finest first; the ground truth ``gt_depth`` (B, 1, H, W) [m], valid where
    ``mask`` (B, 1, H, W) bool, is brought to
    each scale by averaging its valid log depths in blocks (``avg_pool``).
    """
    _check(pred_depths[0], gt_depth, mask)
    total = pred_depths[0].new_zeros(())
    log_gt = torch.where(mask, torch.log(torch.where(mask, gt_depth, torch.ones_like(gt_depth))), 0.0)
    valid = mask.to(gt_depth.dtype)
    for pred in pred_depths:
        factor = gt_depth.shape[-1] // pred.shape[-1]
        if factor > 1:
            weight = F.avg_pool2d(valid, factor, ceil_mode=True)
            log_s = F.avg_pool2d(log_gt, factor, ceil_mode=True) / weight.clamp(min=1e-6)
            mask_s = weight > 0.999
        else:
            log_s, mask_s = log_gt, mask
        log_s, mask_s = log_s[..., : pred.shape[-2], : pred.shape[-1]], mask_s[..., : pred.shape[-2], : pred.shape[-1]]
        R = torch.where(mask_s, torch.log(pred) - log_s, 0.0)
        grad = kornia.filters.spatial_gradient(R, mode="sobel", normalized=True)   # (B, 1, 2, H, W)
        inner = -F.max_pool2d(-mask_s.to(R.dtype), 3, 1, 1) > 0.5                   # all 3x3 neighbours valid
        n = inner.flatten(1).sum(1).clamp(min=1)          # per image, so the loss is a mean over the batch
        total = total + ((grad.abs().sum(2) * inner).flatten(1).sum(1) / n).mean()
    return total


def teacher_loss(pred_depths, gt_depth: torch.Tensor, mask: torch.Tensor, *, lam: float = LAMBDA,
                 variance_weight: float = 1.0) -> torch.Tensor:
    """``L_si + lam * L_grad`` (EvtSlowTV eq. 14) on the finest prediction and all scales, a scalar tensor ():
    ``pred_depths`` ((B, 1, H_s, W_s) [m], finest first) and ``gt_depth`` (B, 1, H, W) [m], ``mask`` (B, 1, H, W)
    bool as :func:`gradient_matching_loss`; ``variance_weight`` as :func:`scale_invariant_loss`."""
    return (scale_invariant_loss(pred_depths[0], gt_depth, mask, variance_weight=variance_weight)
            + lam * gradient_matching_loss(pred_depths, gt_depth, mask))


def speed_loss(twist: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
    """Mean over the windows of known speed of ``(|v| / speed - 1)^2``; 0 when no speed is known.

    The contrast objective rescales ``v`` to the known speed (it sees only inverse depth x speed), so
    it never trains the magnitude of the predicted ``v``; this term does (a network must give metric
    speeds where no speed is known, at inference), and it keeps ``|v|`` away from 0, where the
    rescaling's gradient (``speed / |v|``) explodes.

    Parameters
    ----------
    twist : Tensor (B, 6) [m/s, rad/s]
    speed : Tensor (B,) [m/s], NaN where unknown.

    Returns
    -------
    Tensor, shape ()
    """
    known = ~torch.isnan(speed)
    if not bool(known.any()):
        return twist.new_zeros(())
    norm = twist[known, :3].norm(dim=-1)
    return ((norm / speed[known].clamp(min=1e-6) - 1.0) ** 2).mean()


def student_loss(inverse_depth: torch.Tensor, twist: torch.Tensor, events: EventWindows, *,
                 teacher_inverse_depth: torch.Tensor | None, lam: float = LAMBDA,
                 objective=SHARED_OBJECTIVE, speed_weight: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """``L_contrast + (1 - lam) * L1(teacher, student) + speed_weight * L_speed`` (EvtSlowTV eq. 15 and
    :func:`speed_loss`); without a teacher no L1 term.

    Parameters
    ----------
    inverse_depth : Tensor (B, 1, H, W) [1/m]
    twist : Tensor (B, 6) [m/s, rad/s]
    events : cmax.contrast.EventWindows
        The raw events of the B windows, their intrinsics and (the metric anchor) known speeds.
    teacher_inverse_depth : Tensor (B, 1, H, W) or None
        The frozen teacher's prediction (no gradient flows into it); None for fine-tuning.
    objective : callable
        ``objective(events, DepthMotion) -> (B,)``; default the shared one, :data:`cmax.contrast.SHARED_OBJECTIVE`.
    speed_weight : float
        Weight of :func:`speed_loss` on the windows whose ``events.speed`` is known.

    Returns
    -------
    (loss, terms) : the scalar loss (``L_contrast`` averaged over the windows) and its terms as floats.
    """
    if not isinstance(events, EventWindows):
        raise TypeError(f"events must be a cmax.contrast.EventWindows, got {type(events).__name__}")
    l_contrast = objective(events, DepthMotion(inverse_depth, twist)).mean()
    terms = {"contrast": float(l_contrast.detach())}
    loss = l_contrast
    if speed_weight > 0 and events.speed is not None:
        l_speed = speed_loss(twist, events.speed.to(twist.dtype))
        terms["speed"] = float(l_speed.detach())
        loss = loss + speed_weight * l_speed
    if teacher_inverse_depth is None:
        return loss, terms
    l1 = (inverse_depth - teacher_inverse_depth.detach()).abs().mean()
    terms["l1_teacher"] = float(l1.detach())
    return loss + (1.0 - lam) * l1, terms
