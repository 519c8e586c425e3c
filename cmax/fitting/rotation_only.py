"""Does a rotation alone explain a se3 window? The model-selection test of a fitted translation.

A se3 fit always finds *some* translation and depth: on a camera that only turns (a pan, a hovering drone
yawing) the depth is unobservable, yet the fit trades part of the rotation for an invented translation and
reports pixels of parallax of its own making, with the rotation off by tens of percent. Its parallax cannot
vouch for itself; the events can: :func:`rotation_only_test` fits the best rotation-only explanation of the
same events (:class:`cmax.fitting.pipeline.RotationStage` on the window's own se3 contrast, from the fit's
rotation plus the rotation whose flow best matches its translation's) and compares it with the se3 fit on
that same objective, cell by cell over the image (the cells of the flow and rotation motion test,
:func:`cmax.fitting.quality.motion_within_noise`), with the noise of the ambiguity test: the rotation-only motion
is one more alternative of the fit, and it is within noise as an alternative is:

    gain_c = (C_c(se3 fit) - C_c(rotation only)) / C(unwarped)     (cell c's share of the contrast difference)
    G      = sum_c gain_c
    noise  = noise_sigmas * sqrt(P) * std_c(gain_c)                 (P: cells with events)
    rotation explains the window when G <= noise

The se3 model holds the rotation-only one (zero translation), so ``G`` is what the translation and the depth
add; within noise they add nothing the events support: the verdict is ``low_parallax``
(:attr:`cmax.fitting.quality.LowMotionCause.ROTATION_ONLY`), and the fit reports the rotation-only rotation when
it scores at least as well as the se3 fit (``G <= 0``, :func:`reports_rotation_only`), else the se3 fit's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from cmax.fitting.pipeline import Motion, RotationStage
from cmax.fitting.quality import _cell_gains, _unit_flows
from cmax.fitting.settings import QualitySettings
from cmax.fitting.window import Window
from cmax.warp import warp_rotation

__all__ = ["RotationOnly", "fit_rotation_only", "rotation_only_test", "reports_rotation_only", "rotation_only_reason"]


@dataclass(frozen=True, eq=False)
class RotationOnly:
    """The rotation-only explanation of a se3 window: its angular velocity ``omega`` (3,) [rad/s], the summed
    gain ``gain`` of the se3 fit over it (> 0: the se3 fit sharpens the image more), its ``noise`` and whether
    the gain is within it (``within_noise``)."""

    omega: np.ndarray
    gain: float
    noise: float
    within_noise: bool


def _rotation_start(w, v: np.ndarray, omega: np.ndarray, rho: torch.Tensor, samples: int = 2000) -> np.ndarray:
    """The rotation (3,) [rad/s] whose flow best matches the se3 motion ``(v, omega)`` at the events' inverse
    depths ``rho`` (N,) [1/m] (least squares over at most about ``samples`` of ``w``'s events): where the fit
    traded rotation for translation, this undoes the trade."""
    step = max(1, w.ev.rays.shape[0] // samples)
    rays, rho = w.ev.rays[::step], rho[::step]
    translation, rotation = _unit_flows(rays, w.ev.K, rho, v, 1e-3)
    d, *_ = np.linalg.lstsq(rotation, translation, rcond=None)
    return np.asarray(omega, float) + d


def fit_rotation_only(w, v: np.ndarray, omega: np.ndarray, rho: torch.Tensor, solver,
                      max_events: int) -> np.ndarray:
    """The best rotation-only angular velocity (3,) [rad/s] of window ``w`` (a
    :class:`cmax.fitting.window.Window`) on its own contrast: :class:`cmax.fitting.pipeline.RotationStage` on at
    most ``max_events`` of its events (``w`` itself when it holds no more; else drawn again from its source),
    from :func:`_rotation_start` of the se3 fit ``(v (3,) [m/s], omega (3,) [rad/s])`` with the events' inverse
    depths ``rho`` (N,) [1/m], through ``solver`` (a :class:`cmax.fitting.solvers.Solver`). Solved at full
    resolution only (``image_scales=(1,)``): that start lies near the optimum, where the coarse scales of the
    rotation fit's schedule, whose job is to reach it from afar, barely change the test's gain and cost a third
    of its time (measured on held-out windows: docs/quality.md)."""
    small = w
    if w.source is not None and len(w.ev.x) > max_events:
        small = Window.from_events(w.source, w.ev.K.double().numpy(), replace(w.settings, max_events=max_events),
                                   w.grid.shape, w.sensor)
    small = replace(small, settings=replace(small.settings, image_scales=(1,)))
    motion, _ = RotationStage().run(small, Motion(omega=_rotation_start(w, v, omega, rho)), solver)
    return np.asarray(motion.omega, float)


def rotation_only_test(w, x: torch.Tensor, y: torch.Tensor, omega_rotation: np.ndarray,
                       settings: QualitySettings) -> RotationOnly:
    """Compare the se3 fit of window ``w`` (its events warped by the fit to the ``B`` reference times of ``w.dt``:
    ``x, y`` (B, N) [px]) with the rotation ``omega_rotation`` (3,) [rad/s] alone on ``w``'s contrast, cell by
    cell over ``settings.motion_cells`` (see the module docstring); ``settings.noise_sigmas`` standard errors
    are noise."""
    omega_rotation = np.asarray(omega_rotation, float)
    with torch.no_grad():
        xr, yr = warp_rotation(w.ev.rays, w.dt, torch.as_tensor(omega_rotation, dtype=w.ev.x.dtype), w.ev.K)
    (fit, used_fit), (rotation, used_rotation) = _cell_gains(w, settings.motion_cells, (x, y), (xr, yr))
    difference = (fit - rotation)[used_fit | used_rotation]
    gain = float(difference.sum())
    if difference.size < 2:
        return RotationOnly(omega_rotation, gain, math.inf, True)
    noise = settings.noise_sigmas * float(np.std(difference, ddof=1)) * math.sqrt(difference.size)
    return RotationOnly(omega_rotation, gain, noise, bool(gain <= noise))


def reports_rotation_only(test: RotationOnly) -> bool:
    """Whether the fit reports the rotation-only rotation of ``test`` (:func:`rotation_only_test`): when it scores
    at least as well as the se3 fit on the same objective (``gain <= 0``). Within noise but below the se3 fit the
    se3 fit's rotation stays: a translating window whose translation a rotation nearly copies keeps what it fitted.

    >>> reports_rotation_only(RotationOnly(np.zeros(3), -0.01, 0.03, True))
    True
    >>> reports_rotation_only(RotationOnly(np.zeros(3), 0.01, 0.03, True))
    False
    """
    return bool(test.within_noise and test.gain <= 0)


def rotation_only_reason(test: RotationOnly, parallax_px: float | None) -> str:
    """The ``low_parallax`` reason of a se3 window that a rotation alone explains (``test`` from
    :func:`rotation_only_test`, within noise); ``parallax_px`` the se3 fit's ``FitResult.parallax_px`` [px]. It
    says which rotation the fit reports (:func:`reports_rotation_only`).

    >>> rotation_only_reason(RotationOnly(np.zeros(3), 0.01, 0.03, True), 8.0)[:72]
    'a rotation alone explains the events within noise (the se3 fit gains 0.0'
    """
    parallax = "" if parallax_px is None else f"; its {parallax_px:.2f} px of parallax are the fit's own"
    omega = ", ".join(f"{value:.4g}" for value in test.omega)
    which = ("the rotation reported is the rotation-only fit's, which scores at least as well (the se3 fit's "
             "motion: quality.replaced)" if reports_rotation_only(test) else
             f"the rotation reported is the se3 fit's, which scores higher within noise (the rotation-only fit's: "
             f"({omega}) rad/s)")
    return (f"a rotation alone explains the events within noise (the se3 fit gains {test.gain:.3g} over it, noise "
            f"{test.noise:.3g}): the translation and the depth are not measured{parallax}; {which}")
