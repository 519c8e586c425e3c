"""The contrast core: events of one or many windows, warps, images of warped events, and objectives.

Everything here is differentiable torch and knows nothing about stages or
solvers: :class:`EventWindows` (the events of B windows), the warps of
:mod:`cmax.warp`, the images of :mod:`cmax.iwe`, and the objectives
``objective(batch, params) -> (B,)`` of :mod:`cmax.contrast.objectives`.
:data:`SHARED_OBJECTIVE` is the depth-and-motion objective that :mod:`learned`
trains on (see ``docs/contrast_objective.md``). The objectives the fit's se3
stages optimise live here too: the patch-wise contrasts of
:mod:`cmax.contrast.patches` (:class:`PatchFlowContrast`, :class:`PatchMotionContrast`)
and the plane sweep's cost of :mod:`cmax.contrast.sweep` (:class:`SweepNodeCost`);
:mod:`cmax.contrast.cells` splits a contrast over the cells of a grid.
"""
from cmax.contrast.batch import EventWindows
from cmax.contrast.cells import contrast_by_cell
from cmax.contrast.objectives import (
    SHARED_OBJECTIVE, AverageTimestamp, CollapseGuard, CrossFit, DepthMotion, GlobalContrast, HeldOutSplit,
    LocalContrast, PlaneVote, SweepVote, VoteNormaliser, WeightedSum, event_inverse_depth, twist_at_speed,
    warp_windows,
)
from cmax.contrast.patches import Patches, PatchFlowContrast, PatchMotionContrast, cut_patches
from cmax.contrast.sweep import SweepNodeCost
from cmax.iwe import accumulate_bilinear, accumulate_bilinear_indexed, blur, image_of_warped_events, polarity_images
from cmax.iwe import sample_bilinear
from cmax.warp import DepthGrid, WarpEvents, project, warp_flow, warp_rotation, warp_se3

__all__ = [
    "EventWindows", "DepthMotion", "SHARED_OBJECTIVE", "AverageTimestamp", "SweepVote", "PlaneVote",
    "VoteNormaliser", "CrossFit", "HeldOutSplit", "LocalContrast",
    "GlobalContrast", "CollapseGuard", "WeightedSum", "event_inverse_depth", "twist_at_speed", "warp_windows",
    "Patches", "cut_patches", "PatchFlowContrast", "PatchMotionContrast", "SweepNodeCost", "contrast_by_cell",
    "accumulate_bilinear", "accumulate_bilinear_indexed", "blur", "image_of_warped_events", "polarity_images",
    "sample_bilinear", "DepthGrid", "WarpEvents", "project", "warp_flow", "warp_rotation", "warp_se3",
]
