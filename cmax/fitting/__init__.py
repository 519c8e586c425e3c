"""Contrast maximization solvers: one window (:func:`fit`) and a whole recording (:func:`fit_sequence`).

Modules, in the order a reader meets them: ``api`` (the public :func:`fit` and :class:`FitResult`),
``settings`` (:class:`FitSettings` and its nested sub-settings), ``window`` (the frozen input every
stage reads), ``pipeline`` (the stage order of each model on one screen, and the stages),
``patch_flow`` (patch flows and the motion-field equations), ``motion`` (the patch-wise refinement
objective), ``depth_sweep`` (the plane sweep of inverse depth), ``solvers`` (scipy, casadi, torch: the
one solve path), ``sequence`` (:func:`fit_sequence`); the command ``cmax fit`` is :mod:`cmax.cli.fit`.
The public names load on first use (they import torch), so that the command line's parser starts fast.
"""
from cmax._lazy import lazy_exports

_LAZY = {
    "FitResult": "cmax.fitting.api", "fit": "cmax.fitting.api",
    "LowParallaxWarning": "cmax.fitting.api", "LowMotionWarning": "cmax.fitting.api",
    "BoundWarning": "cmax.fitting.api", "FitSettings": "cmax.fitting.settings",
    "MotionInit": "cmax.fitting.settings", "Refinement": "cmax.fitting.settings", "Polish": "cmax.fitting.settings",
    "PatchFlowSettings": "cmax.fitting.settings", "RefineSettings": "cmax.fitting.settings",
    "SweepSettings": "cmax.fitting.settings", "StageLog": "cmax.fitting.pipeline",
    "SequenceResult": "cmax.fitting.sequence", "fit_sequence": "cmax.fitting.sequence",
    "fit_windows": "cmax.fitting.batch", "WindowFitError": "cmax.fitting.batch",
    "Verdict": "cmax.fitting.quality", "QualitySettings": "cmax.fitting.quality", "Quality": "cmax.fitting.quality",
    "LowMotionCause": "cmax.fitting.quality",
}

__all__ = ["BoundWarning", "FitResult", "FitSettings", "LowMotionCause", "LowMotionWarning", "LowParallaxWarning",
           "MotionInit", "PatchFlowSettings", "Polish", "Quality", "QualitySettings", "RefineSettings", "Refinement",
           "SequenceResult", "StageLog", "SweepSettings",
           "Verdict", "WindowFitError", "fit", "fit_sequence", "fit_windows"]

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
