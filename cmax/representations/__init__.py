"""Dense event representations: voxel grid (event volume), event frame, time surface.

Each representation is a pure function of a window of events, given either as
:class:`~cmax.events.Events` (numpy in, numpy out) or as
:class:`~cmax.events.EventTensors` (torch in, torch out on the tensors'
device). Outputs are float32 and channel-first:

=====================  ===============  ==============================================
function               shape            value
=====================  ===============  ==============================================
:func:`voxel_grid`     (B, H, W)        signed polarity spread linearly over B bins
:func:`event_frame`    (2, H, W)        event counts, channel 0 = OFF, 1 = ON
                       (H, W)           ``signed=True``: sum of signed polarities
:func:`time_surface`   (2, H, W)        ``exp(-(t_ref - t_last) / tau)``, 0 if no event
=====================  ===============  ==============================================

:func:`voxel_grid_batch` stacks voxel grids of several windows, (K, B, H, W),
in one torch pass. Sums never use ``np.add.at``: numpy goes through
``np.bincount`` (and exploits the time order of :class:`Events`), torch through
``index_add_``; the time surface's per-pixel maximum uses ``np.maximum.at`` /
``scatter_reduce_``. Inputs are never modified.

Reference: A. Z. Zhu, L. Yuan, K. Chaney, K. Daniilidis, "Unsupervised
event-based learning of optical flow, depth, and egomotion", CVPR 2019,
doi:10.1109/CVPR.2019.00108 (the event volume of EvtSlowTV section 4.1).

The modules: :mod:`~cmax.representations.voxel` (voxel grids),
:mod:`~cmax.representations.frames` (event frame and time surface) and
:mod:`~cmax.representations._common` (input checks, flat indices, chunking).
"""
from __future__ import annotations

from cmax.representations.frames import EventFrame, TimeSurface, event_frame, time_surface
from cmax.representations.voxel import VoxelGrid, voxel_grid, voxel_grid_batch

__all__ = [
    "voxel_grid",
    "voxel_grid_batch",
    "event_frame",
    "time_surface",
    "VoxelGrid",
    "EventFrame",
    "TimeSurface",
]
