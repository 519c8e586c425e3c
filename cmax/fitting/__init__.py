"""Contrast maximization solvers: one window (:func:`fit`) and a whole recording (:func:`fit_sequence`).

Modules: ``window`` (the public :func:`fit`, :class:`FitResult`, :class:`FitSettings`),
``sequence`` (:func:`fit_sequence`), ``stages`` (rotation, translation starts, depth, coarse to
fine), ``depth_sweep`` (per-cell plane sweep of inverse depth), ``patch_flow`` (motion from
patch flows), ``motion`` (the local motion refinement), ``solvers`` (scipy, casadi, torch back
ends), ``cli`` (``cmax fit``). The public names load on first use (they import torch), so that
``cmax.fitting.cli`` and the command line's parser start fast.
"""
from cmax._lazy import lazy_exports

_LAZY = {
    "FitResult": "cmax.fitting.window", "FitSettings": "cmax.fitting.window", "fit": "cmax.fitting.window",
    "LowParallaxWarning": "cmax.fitting.window",
    "SequenceResult": "cmax.fitting.sequence", "fit_sequence": "cmax.fitting.sequence",
}

__all__ = ["FitResult", "FitSettings", "LowParallaxWarning", "SequenceResult", "fit", "fit_sequence"]

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
