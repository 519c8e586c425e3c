"""Contrast maximization solvers: one window (:func:`fit`) and a whole recording (:func:`fit_sequence`).

Modules: ``window`` (the public :func:`fit`, :class:`FitResult`, :class:`FitSettings`),
``sequence`` (:func:`fit_sequence`), ``stages`` (rotation, translation starts, depth, coarse to
fine), ``depth_sweep`` (per-cell plane sweep of inverse depth), ``patch_flow`` (motion from
patch flows), ``solvers`` (scipy, casadi, torch back ends), ``cli`` (``cmax fit``).
"""
from cmax.fitting.sequence import SequenceResult, fit_sequence
from cmax.fitting.window import FitResult, FitSettings, fit

__all__ = ["FitResult", "FitSettings", "SequenceResult", "fit", "fit_sequence"]
