"""EMVS baseline: event-based multi-view stereo by space-sweep voting (Rebecq et al., IJCV 2018).

A recording with its trajectory (needs the files; an example on synthetic events: :mod:`cmax.emvs.core`):

>>> from cmax.emvs import EMVS, read_tum_trajectory
>>> result = EMVS(camera, depth_range=(0.47, 2.4)).run(events, read_tum_trajectory("groundtruth.txt"))  # doctest: +SKIP
>>> result.plot("depth.png"); result.save_ply("points.ply")                                            # doctest: +SKIP

Modules: :mod:`~cmax.emvs.core` (the :class:`EMVS` driver), :mod:`~cmax.emvs.dsi`
(planes, affine transfer, voting), :mod:`~cmax.emvs.result` (DSI to
semi-dense depth, pictures, PLY), :mod:`~cmax.emvs.poses` (pose inputs, TUM files).
"""
from cmax.emvs.core import EMVS
from cmax.emvs.poses import as_trajectory, read_tum_trajectory
from cmax.emvs.result import DSI, NoBaselineWarning, SemiDenseDepth, semi_dense_depth, write_ply

__all__ = ["EMVS", "DSI", "SemiDenseDepth", "semi_dense_depth", "read_tum_trajectory", "as_trajectory",
           "write_ply", "NoBaselineWarning"]
