"""Settings of :func:`cmax.fit`: every tuned constant of the fit, in frozen dataclasses validated at construction.

:class:`FitSettings` holds the window-wide options and four nested sub-settings: one per se3 stage
that has constants of its own, :class:`PatchFlowSettings` (the patch-flow initialiser),
:class:`RefineSettings` (the patch-wise refinement) and :class:`SweepSettings` (the depth sweep's
second-level constants), and :class:`QualitySettings` (the verdict: the ambiguity test, the low-motion
test and the resolution of ambiguous windows from their neighbours). Strategies are enums
(:class:`MotionInit`, :class:`Refinement`, :class:`Polish`); their string values are accepted and turned
into the enum. Stopping tolerances are :class:`cmax.fitting.solvers.Tolerances`. Why each default is
what it is: ``docs/fitting.md``.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from cmax.fitting.solvers import RELAXED_TOLERANCES, SCIPY_DEFAULT_TOLERANCES, Tolerances
from cmax.hot_pixels import HotPixelFilter, check_filter

__all__ = ["FitSettings", "MotionInit", "Refinement", "Polish", "PatchFlowSettings", "RefineSettings",
           "SweepSettings", "QualitySettings", "LOW_PARALLAX_PX", "PROBE_TIMES", "BASE_MAX_EVENTS",
           "max_events_for"]

LOW_PARALLAX_PX = 1.0
"""Default of :attr:`FitSettings.low_parallax_px`: below this median displacement [px] of the events by the
translation over the window, :func:`cmax.fit` warns (:class:`cmax.fitting.LowParallaxWarning`)."""

BASE_MAX_EVENTS = 60_000
"""The events :func:`cmax.fit` keeps of a window on an image of at most 346x260 pixels when
:attr:`FitSettings.max_events` is None (its default); a larger image keeps more (:func:`max_events_for`)."""

#: The image area [px] (a DAVIS346's) up to which the default subsample is :data:`BASE_MAX_EVENTS`.
MAX_EVENTS_AREA = 346 * 260


def max_events_for(max_events: int | None, width: int, height: int) -> int:
    """The events kept of a window on a ``width`` x ``height`` image [px]: ``max_events`` when it is given;
    None (``FitSettings.max_events``' default): :data:`BASE_MAX_EVENTS` on an image of at most 346x260 pixels,
    on a larger one that many times ``sqrt(width height / (346 260))``, the sensor's side over a DAVIS346's:
    the scale by which :func:`cmax.fitting.quality.density_pixels` counts the pixels of the sparse-window rule,
    so the default keeps the same margin over that rule's need on every sensor (docs/quality.md).

    >>> max_events_for(None, 346, 260), max_events_for(None, 160, 120), max_events_for(30_000, 1280, 720)
    (60000, 60000, 30000)
    >>> max_events_for(None, 640, 480), max_events_for(None, 1280, 720)
    (110876, 192043)
    """
    if max_events is not None:
        return int(max_events)
    area = int(width) * int(height)
    if area <= 0:
        raise ValueError(f"the image must have pixels, got {width}x{height}")
    return BASE_MAX_EVENTS if area <= MAX_EVENTS_AREA else round(BASE_MAX_EVENTS * math.sqrt(area / MAX_EVENTS_AREA))


PROBE_TIMES = (-1.0, -0.5, 0.5, 1.0)
"""Default of :attr:`FitSettings.collapse_times`: the time offsets the deformation guard warps its probes
by, in units of the window's duration."""


class MotionInit(str, enum.Enum):
    """How the se3 motion starts: patch flows fitted to the motion-field equations, or a rotation fit
    then translation directions from several starts on the global contrast."""

    PATCHES = "patches"
    STARTS = "starts"


class Refinement(str, enum.Enum):
    """How the se3 motion is refined after its start: on the patch-wise contrast, or not at all."""

    LOCAL = "local"
    NONE = "none"


class Polish(str, enum.Enum):
    """The se3 fit's final stage on :data:`cmax.contrast.SHARED_OBJECTIVE` (the objective :mod:`learned`
    trains on; :mod:`cmax.fitting.polish`): none, the inverse-depth grid alone, or the grid with the
    translation direction and angular velocity (``|v|`` held)."""

    NONE = "none"
    DEPTH = "depth"
    DEPTH_MOTION = "depth_motion"


def _grid(name: str, value: object) -> tuple[int, int]:
    try:
        rows, cols = (int(a) for a in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (rows, cols), got {value!r}") from None
    if rows < 1 or cols < 1 or (rows, cols) != tuple(value):
        raise ValueError(f"{name} must be two positive integers (rows, cols), got {value!r}")
    return rows, cols


def _positive_int(name: str, value: object, minimum: int = 1) -> None:
    if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _positive(name: str, value: object) -> None:
    if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")


def _fraction(name: str, value: object) -> None:
    if not (isinstance(value, (int, float, np.number)) and 0 <= value <= 1):
        raise ValueError(f"{name} must be in [0, 1], got {value!r}")


def _non_negative(name: str, value: object) -> None:
    if not (isinstance(value, (int, float, np.number)) and not isinstance(value, bool) and np.isfinite(value)
            and value >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


def _tolerances(name: str, value: object, optional: bool = False) -> None:
    if not (isinstance(value, Tolerances) or (optional and value is None)):
        raise TypeError(f"{name} must be a cmax.fitting.solvers.Tolerances{' or None' if optional else ''}, "
                        f"got {value!r}")


@dataclass(frozen=True)
class PatchFlowSettings:
    """The patch-flow initialiser of se3 (:mod:`cmax.fitting.patch_flow`).

    Attributes
    ----------
    grid : (rows, cols)
        Patches over the image.
    min_events : int
        Patches with fewer (subsampled) events are left out.
    max_events : int
        Uniform subsample of the window's events (the default, equal to ``FitSettings.max_events`` up to 346x260
        pixels, takes them all there: each patch's flow is then sharper, and the motion-field fit that starts the
        refinement steadier; docs/fitting.md; on a larger image it takes 60,000 of the window's more).
    margin : float
        Largest displacement over the window, as a fraction of the patch side (at least 8 px).
    sigmas : tuple of (float or None)
        Blur [px] of each coarse-to-fine level; None: the window's ``sigma``.
    iterations : int
        Solver iterations of each level.
    coarse_step : int
        Every level but the last uses every ``coarse_step``-th event.
    directions : int
        Candidate translation directions of the motion-field fit (Fibonacci sphere).
    cap_directions : int
        Directions of the finer cap around the best (0: no cap).
    cap_radius : float
        Radius of that cap, in spacings of the ``directions`` on the sphere (``sqrt(4 pi / directions)`` rad).
    negative_depth_penalty : float
        A direction's motion-field residual is multiplied by ``1 + negative_depth_penalty * x``, ``x`` the
        fraction of its patches' inverse depths that come out negative.
    min_margin_px : int
        Smallest ``margin`` [px], whatever the patch side.
    min_patches : int
        With fewer patches holding ``min_events``, the stage falls back to the rotation and translation
        starts (the motion-field equations need the patches' spread).
    information_step_px : float
        Step [px of displacement over the window] of the central differences of each patch's contrast
        curvature (:func:`cmax.fitting.patch_flow.flow_information`).
    information_floor : float
        The curvature's eigenvalues are clipped to at least this fraction of the largest over all patches.
    tolerances : Tolerances
        Stopping tolerances of each level's solve: ``ftol`` 1e-7 (scipy's default spent most evaluations on
        the last sliver of the decrease, for no measured accuracy: ``docs/fitting.md``), scipy's ``gtol``.
    """

    grid: tuple[int, int] = (4, 5)
    min_events: int = 200
    max_events: int = 60_000
    margin: float = 0.4
    sigmas: tuple[float | None, ...] = (3.0, None)
    iterations: int = 40
    coarse_step: int = 3
    directions: int = 3000
    cap_directions: int = 400
    cap_radius: float = 1.5
    negative_depth_penalty: float = 4.0
    min_margin_px: int = 8
    min_patches: int = 4
    information_step_px: float = 0.25
    information_floor: float = 1e-3
    tolerances: Tolerances = Tolerances(ftol=1e-7, gtol=SCIPY_DEFAULT_TOLERANCES.gtol)

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid", _grid("patch_flow.grid", self.grid))
        _positive_int("patch_flow.min_events", self.min_events)
        _positive_int("patch_flow.max_events", self.max_events)
        _fraction("patch_flow.margin", self.margin)
        if len(self.sigmas) == 0 or any(s is not None and not (np.isfinite(s) and s > 0) for s in self.sigmas):
            raise ValueError(f"patch_flow.sigmas must be positive blurs or None (one at least), got {self.sigmas!r}")
        _positive_int("patch_flow.iterations", self.iterations)
        _positive_int("patch_flow.coarse_step", self.coarse_step)
        _positive_int("patch_flow.directions", self.directions, 2)
        _positive_int("patch_flow.cap_directions", self.cap_directions, 0)
        _positive("patch_flow.cap_radius", self.cap_radius)
        _non_negative("patch_flow.negative_depth_penalty", self.negative_depth_penalty)
        _positive_int("patch_flow.min_margin_px", self.min_margin_px, 0)
        _positive_int("patch_flow.min_patches", self.min_patches, 3)
        _positive("patch_flow.information_step_px", self.information_step_px)
        if not (isinstance(self.information_floor, (int, float, np.number)) and 0 < self.information_floor <= 1):
            raise ValueError(f"patch_flow.information_floor must be in (0, 1], got {self.information_floor!r}")
        _tolerances("patch_flow.tolerances", self.tolerances)


@dataclass(frozen=True)
class RefineSettings:
    """The patch-wise refinement of the se3 motion (:mod:`cmax.fitting.motion`).

    Attributes
    ----------
    grid : (rows, cols)
        Patches, each with its own inverse depth.
    min_events, max_events, margin
        As in :class:`PatchFlowSettings`.
    min_margin_px, min_patches
        As in :class:`PatchFlowSettings` (with fewer patches the refinement keeps its start, and the
        ambiguity test does not run).
    rho_candidates : int
        Inverse depths of the per-patch start sweep, log-uniform over ``depth_range``.
    rho_coarse_step : float
        That sweep first scores candidates this far apart at most in log inverse depth, then the ones around
        each patch's best (:func:`cmax.fitting.motion.sweep_stride`, :func:`~cmax.fitting.motion.strided_argmax`);
        0: every candidate. With the default 0.25 the room's 1-6.5 m takes every third candidate; ranges as wide as the
        default 0.5-60 m (candidates 0.21 apart) take every one, where a patch's contrast over depth can
        have a second peak between coarse candidates.
    iterations : int
        Solver iterations.
    direction_scale : float
        The translation direction enters the solve as ``direction_scale * v / |v|`` [parameter units per
        unit vector], so that a unit step turns it by about ``1 / direction_scale`` rad (10: ~6 deg), like
        one pixel of displacement of the other parameters; each component is bounded by twice it.
    tolerances : Tolerances
        Stopping tolerances of the solve (scipy's L-BFGS-B defaults).
    """

    grid: tuple[int, int] = (6, 8)
    min_events: int = 100
    max_events: int = 20_000
    margin: float = 0.3
    min_margin_px: int = 8
    min_patches: int = 4
    rho_candidates: int = 24
    rho_coarse_step: float = 0.25
    iterations: int = 60
    direction_scale: float = 10.0
    tolerances: Tolerances = SCIPY_DEFAULT_TOLERANCES

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid", _grid("refine.grid", self.grid))
        _positive_int("refine.min_events", self.min_events)
        _positive_int("refine.max_events", self.max_events)
        _fraction("refine.margin", self.margin)
        _positive_int("refine.rho_candidates", self.rho_candidates, 2)
        _non_negative("refine.rho_coarse_step", self.rho_coarse_step)
        _positive_int("refine.iterations", self.iterations)
        _positive_int("refine.min_margin_px", self.min_margin_px, 0)
        _positive_int("refine.min_patches", self.min_patches, 1)
        _positive("refine.direction_scale", self.direction_scale)
        _tolerances("refine.tolerances", self.tolerances)


@dataclass(frozen=True)
class SweepSettings:
    """Second-level constants of the depth sweep (:mod:`cmax.fitting.depth_sweep`).

    Attributes
    ----------
    refine_candidates : int
        Steps of each relative sweep.
    chunk : int
        Candidates warped at once (memory against speed; no effect on the result).
    border_px : int
        A warped event closer than this to the image's edge [px] counts as pushed out of the image (its
        vote is left out of its node's mean; the bilinear vote of an event on the edge row is cut).
    vote_scale_quantile : float
        An event that some candidate pushes out of the image is divided by this quantile (lower
        interpolation: 0.5 is the lower median) of the largest values of the events that every
        candidate keeps inside, instead of its own largest value
        (:class:`cmax.contrast.SweepNodeCost`).
    """

    refine_candidates: int = 13
    chunk: int = 8
    border_px: int = 1
    vote_scale_quantile: float = 0.5

    def __post_init__(self) -> None:
        _positive_int("sweep.refine_candidates", self.refine_candidates, 3)
        _positive_int("sweep.chunk", self.chunk)
        _positive_int("sweep.border_px", self.border_px, 0)
        _fraction("sweep.vote_scale_quantile", self.vote_scale_quantile)


@dataclass(frozen=True)
class QualitySettings:
    """Options of the verdict (:mod:`cmax.fitting.quality`): the ambiguity test of se3, the low-motion test of
    flow and rotation, and the resolution of ambiguous windows from their neighbours.

    Attributes
    ----------
    ambiguity_test : bool
        Score the alternatives (se3 with a fitted direction; a few sweeps of the patch-wise objective).
    margin : float
        Relative margin: an alternative whose summed gain is within ``margin`` times the fit's own
        contrast gain over the unwarped events is ambiguous, whatever the patches' spread.
    noise_sigmas : float
        Multiples of the standard error of the summed per-patch gain that count as noise.
    polish_iterations : int
        Iterations of the fit's own patch-wise refinement (:func:`cmax.fitting.motion.refine_motion_local`)
        from each alternative before it is scored (0: the depth sweep only), so that an alternative is
        compared at its own optimum as the fit is at its.
    distinct_deg : float
        A polished alternative that ends within this distance of the fit (direction angle plus rotation
        over the window, degrees) is the fit itself, not an alternative: it is dropped, unless it lies at least
        ``recheck_deg`` from the fit and scores better than it beyond a tie.
    recheck_deg : float
        A polished alternative that ends within ``distinct_deg`` of the fit but at least this far from it
        (degrees, the same distance) is scored; when it scores better than the fit by more than ``margin`` times the
        fit's own gain it is kept as an alternative, so that the window is at best ``ambiguous``: the fit is then
        not the optimum of its own objective, and its direction may be off by that much or more (docs/quality.md:
        the windows that showed it). ``distinct_deg`` or more turns the check off.
    neighbours : int
        ``fit_sequence``: windows on each side searched for confident (``ok``) neighbours.
    max_resolve_deg : float
        ``fit_sequence``: a candidate farther than this from the neighbours' motion (direction angle
        plus rotation difference over the window, degrees) does not resolve a window.
    motion_test : bool
        ``flow``/``rotation``: test the fitted motion's contrast gain against its spread over the
        image's cells (:func:`cmax.fitting.quality.motion_within_noise`); a gain within noise makes the
        verdict ``low_parallax`` and warns :class:`cmax.fitting.LowMotionWarning`.
    motion_cells : (rows, cols)
        The cells of that test.
    motion_noise_sigmas : float
        Multiples of the standard error of the summed per-cell gain that count as noise.
    shuffle_test : bool
        Every model, with a given pose too: warp the events by the fitted motion once more with their
        timestamps permuted among them (:func:`cmax.fitting.quality.shuffled_gain_test`); when that gains
        at least ``shuffle_fraction`` of the fit's own contrast gain, the gain comes from the image's
        border, not from aligning events in time: the verdict is ``low_parallax`` and the fit warns.
    shuffle_fraction : float
        The fraction of that test, in (0, 1].
    shuffle_events : int
        At most this many events (every k-th) enter that test's images; the rotation-only fit of
        ``rotation_test`` is drawn from at most this many too.
    rotation_test : bool
        se3 with a free rotation (no ``pose``, no ``omega``): fit the best rotation-only explanation of the same
        events and compare the se3 fit with it on the window's contrast, cell by cell over ``motion_cells`` with
        ``noise_sigmas`` (:func:`cmax.fitting.rotation_only.rotation_only_test`); when the se3 fit's gain
        over it is within noise, the translation and depth are not measured: the verdict is ``low_parallax``
        (``LowMotionCause.ROTATION_ONLY``), the fit warns :class:`cmax.fitting.LowParallaxWarning`, and reports the
        rotation-only rotation when it scores at least as well as the se3 fit (docs/quality.md).
    smoothing : bool
        ``fit_sequence``: the motion prior across windows. After the resolution, every se3 window whose
        data cannot tell its own motion from the consensus of its confident neighbours (the median
        direction and rotation of the window and at least ``min_consensus`` of them, scored as an
        alternative: gain within noise) takes the consensus, its depth swept for it
        (:func:`cmax.fitting.sequence.smooth_from_neighbours`).
    min_consensus : int
        ``fit_sequence``: confident neighbours needed to form a consensus.
    smoothing_span_s : float
        ``fit_sequence``: the motion prior's neighbours lie within this many seconds on each side of a
        window (as many windows as the step fits into it, at least ``neighbours``): a prior of steady
        motion over about three seconds, which a window takes only where its data cannot tell its own
        motion from it. A run of a few windows that share a wrong motion (the rotation traded against the
        translation, window after window) is outvoted; a turn, whose windows tell their own motion
        apart from a consensus that far, keeps its fits (docs/quality.md).
    smoothing_min_deg : float
        ``fit_sequence``: a consensus closer than this to the window's own motion (direction angle plus
        rotation over the window, degrees) changes nothing worth a re-fit: the window keeps its fit.
    max_rate_change : float
        se3 with a fitted motion: a window whose busier half holds more than this many times the events of
        its other half (:func:`cmax.fitting.quality.rate_change`; a start or a stop inside it) is
        ``ambiguous`` and ``unsteady``: no constant velocity explains it, and ``fit_sequence`` gives it its
        neighbours' motion. Above 1; ``math.inf`` turns the test off (docs/quality.md: how the value was
        chosen).
    min_event_density : float
        se3 with a fitted direction: a window fitted on fewer events than this per pixel of the image (after
        ``FitSettings.max_events``; on an image larger than ``min_event_density_area``, per pixel of fewer pixels:
        :func:`cmax.fitting.quality.density_pixels`) is at best ``ambiguous`` and ``sparse``: its image of warped
        events holds too few coincidences for the ambiguity test to vouch for the direction (docs/quality.md: the
        measurement behind the value). 0 turns the rule off.
    min_event_density_area : int
        The image area [px] (346x260) up to which ``min_event_density`` is counted over every pixel of the image;
        a larger image counts over ``sqrt(width * height * min_event_density_area)`` pixels (the events lie along
        edges, whose pixels grow with the image's side, not its area): 41,560 events at 640x480, 71,984 at
        1280x720 by default, not 76,800 and 230,400 (docs/quality.md: the measurement on such windows). The
        sensor's own ``width * height`` or more: the density over the whole image.
    max_bound_share : float
        se3 with a fitted motion: a window with at least this share of its events' depth on one end of
        ``FitSettings.depth_range`` (but under ``FitSettings.depth_bound_fraction``, which fails the fit) is at
        best ``ambiguous``, with a ``BoundWarning``: a free motion can tilt until just under that fraction of the
        events leave the bound, so the depth is clipped and the direction bent without the fit failing. In
        (0, 1]; 1 turns the rule off (docs/quality.md: the windows behind the value).
    min_ok_parallax_px : float
        se3 with a fitted direction and a free rotation: a window whose ``FitResult.parallax_px`` is under this
        (but not under ``FitSettings.low_parallax_px``, which makes it ``low_parallax``) is at best ``ambiguous``
        and ``small_parallax``: over a few pixels of parallax a rotation absorbs most of what a turn of the
        translation direction changes in the image (the bas-relief ambiguity), so the contrast can prefer a
        direction tens of degrees off beyond its noise and no alternative of the test flags it. Not applied with
        the rotation held (``omega=``, a gyroscope). 0 turns the rule off (docs/quality.md). On an image of fewer
        pixels than ``min_ok_parallax_area`` the threshold grows (:func:`cmax.fitting.quality.min_ok_parallax`).
    min_ok_parallax_area : int
        The image area [pixels] (346x260) at and above which ``min_ok_parallax_px`` applies as it is; on a smaller
        image it is multiplied by ``sqrt(min_ok_parallax_area / (width height))``: on a quarter of the pixels the
        contrast's optimum lies off the truth beyond its noise far more often, and ``ok`` windows 37-98 deg off
        came with 3.0-5.5 px of parallax at 160x120 (docs/quality.md: the measurement). 1 turns the scaling off.
    max_noise_share : float
        se3, with a given pose too: a window whose events are estimated to be more than this share of uniform
        background-activity noise (:func:`cmax.fitting.quality.noise_share`: isolated events, none other within
        1 px and ``noise_window_us``) is at best ``ambiguous`` and ``noisy``: the noise's pixels enter the depth
        map and pull the depth sweep, with no sign of it in the contrast. In (0, 1]; 1 turns the rule off
        (docs/quality.md: the measurement behind the value).
    noise_window_us : int
        Half the time span [µs] of that test's neighbourhood (the background-activity filter's window).
    bas_relief_turn_deg : float
        se3 with a fitted direction and a free rotation, when the verdict would be ``ok``: the fit's translation
        turned by this many degrees four ways (two perpendicular axes, both signs), each with the rotation that makes
        up the change of its flow (:func:`cmax.fitting.quality.turned_motions`), is scored as an alternative; when
        one scores better than the fit (its gain under 0) the window is at best ``ambiguous`` and ``turned``: the fit
        is not the optimum of its own objective along the bas-relief trade, where a rotation of the wrong size
        explains part of the translation's flow at the price of a depth offset (docs/quality.md: the windows behind
        the value). 0 turns the test off.
    bas_relief_valley_deg : float
        se3 with a fitted direction and a free rotation, when the verdict would still be ``ok``: the fit's translation
        turned by this many degrees the same four ways along the trade, each with the rotation that makes up the
        change of its flow, is scored as an alternative (:func:`cmax.fitting.quality.valley_turned`); when one scores
        within noise of the fit (its gain at most its noise) the window is at best ``ambiguous`` and ``flat_valley``:
        the events do not fix the direction to within this angle, nor the rotation's size and the depth's scale with
        it (docs/quality.md: the windows behind the value, 20 deg). 0, the default, turns the test off: on, it
        made every window of a sliding camera ambiguous, and ``fit_sequence``'s resolution from neighbours then
        left windows of the ECD slider reversed.
    """

    ambiguity_test: bool = True
    margin: float = 0.02
    noise_sigmas: float = 1.0
    polish_iterations: int = 20
    distinct_deg: float = 30.0
    recheck_deg: float = 15.0
    neighbours: int = 2
    max_resolve_deg: float = 45.0
    motion_test: bool = True
    motion_cells: tuple[int, int] = (6, 8)
    motion_noise_sigmas: float = 2.5
    shuffle_test: bool = True
    shuffle_fraction: float = 0.5
    shuffle_events: int = 20_000
    rotation_test: bool = True
    smoothing: bool = True
    min_consensus: int = 2
    smoothing_span_s: float = 1.7
    smoothing_min_deg: float = 1.0
    max_rate_change: float = 6.0
    min_event_density: float = 0.25
    min_event_density_area: int = 346 * 260
    max_bound_share: float = 0.15
    min_ok_parallax_px: float = 3.0
    min_ok_parallax_area: int = 346 * 260
    max_noise_share: float = 0.3
    noise_window_us: int = 10_000
    bas_relief_turn_deg: float = 10.0
    bas_relief_valley_deg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("ambiguity_test", "motion_test", "shuffle_test", "rotation_test", "smoothing"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be a bool, got {getattr(self, name)!r}")
        object.__setattr__(self, "motion_cells", _grid("motion_cells", self.motion_cells))
        for name in ("margin", "noise_sigmas", "distinct_deg", "recheck_deg", "max_resolve_deg",
                     "motion_noise_sigmas", "smoothing_min_deg", "smoothing_span_s", "min_event_density",
                     "min_ok_parallax_px", "bas_relief_turn_deg", "bas_relief_valley_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if isinstance(self.min_ok_parallax_area, bool) or not (isinstance(self.min_ok_parallax_area, int)
                                                               and self.min_ok_parallax_area >= 1):
            raise ValueError(f"min_ok_parallax_area must be an int >= 1 (pixels), got {self.min_ok_parallax_area!r}")
        if isinstance(self.min_event_density_area, bool) or not (isinstance(self.min_event_density_area, int)
                                                                 and self.min_event_density_area >= 1):
            raise ValueError("min_event_density_area must be an int >= 1 (pixels), "
                             f"got {self.min_event_density_area!r}")
        if isinstance(self.max_rate_change, bool) or not (isinstance(self.max_rate_change, (int, float))
                                                          and self.max_rate_change > 1):
            raise ValueError(f"max_rate_change must be a number > 1 (math.inf: no test), got {self.max_rate_change!r}")
        _positive_int("noise_window_us", self.noise_window_us, 1)
        for name in ("shuffle_fraction", "max_bound_share", "max_noise_share"):
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and 0 < value <= 1):
                raise ValueError(f"{name} must lie in (0, 1], got {value!r}")
        if not (isinstance(self.polish_iterations, int) and self.polish_iterations >= 0):
            raise ValueError(f"polish_iterations must be an int >= 0, got {self.polish_iterations!r}")
        _positive_int("shuffle_events", self.shuffle_events, 100)
        for name in ("neighbours", "min_consensus"):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")


@dataclass(frozen=True)
class FitSettings:
    """Options of :func:`cmax.fit` beyond the model, validated at construction.

    Attributes
    ----------
    contrast : {"variance", "gradient"} or None
        Contrast of the IWEs; None picks per model (``"gradient"`` for ``rotation``, ``"variance"``
        for ``flow`` and ``se3``).
    polarity_split : bool or None
        Image ON and OFF events apart in the motion contrast and add the two contrasts; None picks
        per model (True for ``rotation``, False for ``flow`` and ``se3``).
    references : tuple of float
        Reference times of the multi-reference motion objective, as fractions of the window.
    sigma : float
        IWE blur [px].
    max_events : int or None
        Windows with more events are subsampled uniformly (seeded) to this many. None (the default): by the
        sensor, :func:`max_events_for`: 60,000 (:data:`BASE_MAX_EVENTS`) on an image of at most 346x260 pixels,
        more on a larger one in proportion to its side (110,876 at 640x480, 192,043 at 1280x720), so that the
        sparse-window rule (``QualitySettings.min_event_density``) is cleared with the same margin on any sensor.
        ``60_000``: that many on every sensor (before the scaling).
    depth_range : (float, float)
        Bounds of the depth [m] (in units of ``speed * 1 s`` when the scale is unknown); give the
        scene's own range when it is known.
    depth_candidates : int
        Inverse depths of the plane sweep (uniform in inverse depth over ``depth_range``; over a wide range
        :func:`cmax.fitting.depth_sweep.sweep_candidates` adds a few at its far end, spaced as the first of
        ``depth_refinements`` reaches: the widest).
    depth_smoothness : (float, float)
        Semi-global matching penalties ``(P1, P2)`` of the sweep, in units of the median node confidence.
    depth_coarsening : int
        The sweep over the whole range runs on a grid this many times coarser than ``depth_grid``.
    depth_refinements : tuple of float
        Half-widths (log of a factor) of the relative sweeps that follow the first one.
    depth_bound_fraction : float
        When at least this share of the events' depth (by their grid weights) ends on one end of
        ``depth_range`` (within half a sweep step), the sweep reports that bound (``depth_near`` /
        ``depth_far``): a ``BoundWarning``, ``success`` False. Under it the shares are only noted in the
        stage's message.
    motion_init : MotionInit or str
        ``"patches"`` (patch flows and the motion-field equations) or ``"starts"``.
    motion_refinement : Refinement or str
        ``"local"`` (the patch-wise contrast, each patch with its own depth) or ``"none"``.
    zero_rotation_start : bool
        A second start of the ``"local"`` refinement: the motion-field fit with the rotation held at
        zero (for vehicles); the refined motion with the higher patch-wise contrast wins.
    motion_members : int
        se3 (``motion_init="patches"``): run the motion stages (patch flows, local refinement) on this many
        draws of the window, each with its own subsampling and dither seed (the first is ``seed``), and
        continue from their consensus (:class:`cmax.fitting.pipeline.MotionMembersStage`). The refinement
        stops at a point of a nearly flat valley of its objective that moves with the draw; the draws'
        consensus lies nearer the truth than one draw does, at the members' cost in time
        (``docs/fitting.md``). 1: one draw, the window itself.
    members_agree_deg : float
        The consensus is the mean motion of the members within this distance of their medoid (direction
        angle plus the rotation over the window, degrees): a member that went to the mirrored motion does
        not pull the mean.
    polish : Polish or str
        se3's final stage on the shared objective (:mod:`cmax.fitting.polish`): ``"none"``, ``"depth"``
        (the inverse-depth grid) or ``"depth_motion"`` (the grid, the translation direction and the
        angular velocity; with ``pose=`` or ``omega=`` the known part is held).
    polish_iterations : int
        Iteration limit of the polish's solve.
    alternations : int
        Rounds of (motion with the depth held, depth sweep) after the first depth (se3 without pose).
    collapse_weight : float
        Weight of the deformation guard (:func:`cmax.objectives.deformation`).
    collapse_lattice : (rows, cols)
        Probe pixels of the deformation guard, spread over 10-90 % of the image.
    collapse_times : tuple of float
        Time offsets the deformation guard warps its probes by, in units of the window's duration.
    translation_starts : int
        Directions tried for the translation with ``motion_init="starts"`` (6: the camera axes; 14
        adds the diagonals).
    iterations : int
        Iteration limit of each solve of the global-contrast stages at full resolution.
    coarse_iterations : int
        Iteration limit of each solve at a coarser image scale.
    image_scales : tuple of int or None
        The coarse-to-fine schedule of the global-contrast stages (``flow``, ``rotation``): image scales,
        decreasing, ending with 1 (full resolution). None: by the sensor's larger side, ``(4, 2, 1)`` from
        256 px, ``(2, 1)`` from 96 px, else ``(1,)``.
    tolerances : Tolerances or None
        Stopping tolerances of the global-contrast solves of ``rotation``, the se3 translation starts and
        the motion with the depth held (None: the backend's own).
    flow_tolerances : Tolerances
        Stopping tolerances of the ``flow`` solves (looser: a 2-parameter flow is below 0.1 px of error
        well before the backend's own tolerances stop it).
    start_iterations : int
        Iteration limit of each translation start (``motion_init="starts"``, at image scale 2).
    max_omega : float
        Bound of each angular-velocity component [rad/s]. A fit that ends on it is reported
        (``FitResult.success`` False and a :class:`cmax.fitting.BoundWarning`), never clipped silently.
    max_flow_px : float
        Bound of each flow component, as a displacement over the window in units of the sensor's
        larger side (2: twice the width).
    low_motion_px : float
        ``flow`` and ``rotation``: below this median displacement of the events over the window [px]
        the fit warns (:class:`cmax.fitting.LowMotionWarning`).
    low_parallax_px : float
        se3: below this median displacement of the events by the translation over the window [px]
        (``FitResult.parallax_px``) the fit warns (:class:`cmax.fitting.LowParallaxWarning`) and the
        verdict is ``low_parallax``.
    min_cell_events : int
        Depth cells with fewer events are outside the mask.
    mask_isolated_us : int
        Pixels that only isolated events reach (none other within 1 px and this many µs:
        :func:`cmax.fitting.quality.isolated_events`, the background-activity filter's test) are outside the
        mask: uniform sensor noise would otherwise put its own pixels into it, each with a depth of its own
        (docs/quality.md). 0 keeps every event pixel.
    min_neighbours : int
        se3: events with fewer than this many other events within 1 px and ``mask_isolated_us`` µs
        (:func:`cmax.fitting.quality.neighbour_counts`, the background-activity filter's support) are left out of
        the fit, motion, depth and mask (``FitResult.events_used`` counts the rest): uniform sensor noise next to
        the scene is not isolated, and without this filter it pulls the depth of the cells it falls in and fills
        cells of its own (docs/quality.md: the measurement). 0 (or ``mask_isolated_us`` 0) keeps every event.
    denoise_min_rate_hz : float
        That filter applies only to a window whose estimated background-activity rate [Hz per pixel] is at least
        this: the share of noise that :func:`cmax.fitting.quality.noise_share` reads, times the events, over the
        pixels and the window's duration. Clean windows read a rate too, their scene's own isolated events, lower
        than this, and are fitted on every event (docs/quality.md: the rates measured on clean and noisy windows).
        0 filters every se3 window.
    denoise_min_window_us : int
        Nor to a window shorter than this [µs]: the isolated-event test looks ``mask_isolated_us`` either side, and
        on a shorter window the scene's own events lie alone so often that its noise rate reads high, and leaving
        them out can bend the motion (docs/quality.md: the real recordings that showed it).
    max_denoised_share : float
        When the window's estimated share of noise, or the share of its events that filter would leave out, is
        over this, the filter leaves out none: the window is then mostly noise or too sparse for the test, and its
        verdict says so (``quality.noisy``, ``quality.sparse``; on pure noise the few events with neighbours would
        be kept and read as a scene). In (0, 1].
    hot_pixels : HotPixelFilter or None
        Which pixels are hot (:class:`cmax.hot_pixels.HotPixelFilter`: more than ``factor`` (8) times the
        99th percentile of the window's per-pixel event counts and more than ``min_events`` (30), or firing
        alone at a steady rate (``neighbour_factor``); a defect or a flickering light, firing without
        motion): their events are left out of the fit
        (``FitResult.hot_pixels`` lists them). None keeps every event.
    seed : int
        Seed of the subsampling.
    patch_flow, refine, sweep
        The nested settings of those stages.
    quality : QualitySettings
        The verdict of the fit (:mod:`cmax.fitting.quality`): the ambiguity test of se3, the low-motion
        test of flow and rotation, and (:func:`cmax.fit_sequence`) the resolution from neighbours.
    """

    contrast: str | None = None
    polarity_split: bool | None = None
    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    max_events: int | None = None
    depth_range: tuple[float, float] = (0.5, 60.0)
    depth_candidates: int = 36
    depth_smoothness: tuple[float, float] = (0.1, 1.0)
    depth_coarsening: int = 2
    depth_refinements: tuple[float, ...] = (0.3, 0.1)
    depth_bound_fraction: float = 0.5
    alternations: int = 0
    motion_init: MotionInit = MotionInit.PATCHES
    motion_refinement: Refinement = Refinement.LOCAL
    zero_rotation_start: bool = False
    motion_members: int = 1
    members_agree_deg: float = 30.0
    polish: Polish = Polish.NONE
    polish_iterations: int = 60
    collapse_weight: float = 0.1
    collapse_lattice: tuple[int, int] = (9, 12)
    collapse_times: tuple[float, ...] = PROBE_TIMES
    translation_starts: int = 6
    iterations: int = 60
    coarse_iterations: int = 20
    image_scales: tuple[int, ...] | None = None
    start_iterations: int = 25
    tolerances: Tolerances | None = None
    flow_tolerances: Tolerances = RELAXED_TOLERANCES
    max_omega: float = 6.0
    max_flow_px: float = 2.0
    low_motion_px: float = 2.0
    low_parallax_px: float = LOW_PARALLAX_PX
    min_cell_events: int = 15
    mask_isolated_us: int = 10_000
    min_neighbours: int = 2
    denoise_min_rate_hz: float = 0.7
    denoise_min_window_us: int = 20_000
    max_denoised_share: float = 0.5
    hot_pixels: HotPixelFilter | None = field(default_factory=HotPixelFilter)
    seed: int = 0
    patch_flow: PatchFlowSettings = field(default_factory=PatchFlowSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    sweep: SweepSettings = field(default_factory=SweepSettings)
    quality: QualitySettings = field(default_factory=QualitySettings)

    def __post_init__(self) -> None:
        if self.contrast not in (None, "variance", "gradient"):
            raise ValueError(f"contrast must be 'variance', 'gradient' or None, got {self.contrast!r}")
        for name in ("polarity_split", "zero_rotation_start"):
            value = getattr(self, name)
            if not (isinstance(value, (bool, np.bool_)) or (value is None and name == "polarity_split")):
                raise TypeError(f"{name} must be True or False{' or None' if name == 'polarity_split' else ''}, "
                                f"got {value!r}")
        for name, kind in (("motion_init", MotionInit), ("motion_refinement", Refinement), ("polish", Polish)):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                raise ValueError(f"{name} must be one of {[k.value for k in kind]}, got {getattr(self, name)!r}") \
                    from None
        try:
            near, far = (float(value) for value in self.depth_range)
        except (TypeError, ValueError):
            raise ValueError(f"depth_range must be two numbers (near, far) in metres, got {self.depth_range!r}") \
                from None
        if not (np.isfinite(near) and np.isfinite(far)):
            raise ValueError(f"depth_range must be finite metres (the sweep spans it), got {self.depth_range}")
        if not 0 < near < far:
            raise ValueError(f"depth_range must satisfy 0 < near < far (metres), got {self.depth_range}")
        object.__setattr__(self, "depth_range", (near, far))   # a list or an array compares equal to its tuple
        _positive_int("seed", self.seed, 0)
        if self.max_events is not None and not (isinstance(self.max_events, (int, np.integer))
                                                and not isinstance(self.max_events, bool) and self.max_events >= 10):
            raise ValueError(f"max_events must be >= 10 (an int) or None (by the sensor), got {self.max_events!r}")
        if not (isinstance(self.depth_coarsening, (int, np.integer)) and self.depth_coarsening >= 1):
            raise ValueError(f"depth_coarsening must be an integer >= 1, got {self.depth_coarsening!r}")
        smoothness = np.asarray(self.depth_smoothness, dtype=float).ravel()
        if smoothness.size != 2 or not np.all(np.isfinite(smoothness)) or np.any(smoothness < 0):
            raise ValueError(f"depth_smoothness must be two non-negative numbers (P1, P2), got "
                             f"{self.depth_smoothness!r}")
        if len(self.references) == 0 or any(not 0 <= r <= 1 for r in self.references):
            raise ValueError(f"references must be fractions of the window in [0, 1], got {self.references!r}")
        for name in ("sigma", "max_omega", "max_flow_px", "low_motion_px", "low_parallax_px"):
            _positive(name, getattr(self, name))
        object.__setattr__(self, "collapse_lattice", _grid("collapse_lattice", self.collapse_lattice))
        times = tuple(self.collapse_times)
        if not times or any(not (isinstance(t, (int, float, np.number)) and np.isfinite(t) and t != 0)
                            for t in times):
            raise ValueError(f"collapse_times must be non-zero fractions of the window, got {self.collapse_times!r}")
        object.__setattr__(self, "collapse_times", tuple(float(t) for t in times))
        _tolerances("tolerances", self.tolerances, optional=True)
        if self.image_scales is not None:
            scales = tuple(self.image_scales)
            if (not scales or scales[-1] != 1 or any(not isinstance(k, (int, np.integer)) or isinstance(k, bool)
                                                     or k < 1 for k in scales)
                    or any(a <= b for a, b in zip(scales, scales[1:]))):
                raise ValueError(f"image_scales must be decreasing integers ending with 1 (or None), got "
                                 f"{self.image_scales!r}")
            object.__setattr__(self, "image_scales", tuple(int(k) for k in scales))
        _tolerances("flow_tolerances", self.flow_tolerances)
        if not (np.isfinite(self.collapse_weight) and self.collapse_weight >= 0):
            raise ValueError(f"collapse_weight must be >= 0, got {self.collapse_weight!r}")
        _positive_int("depth_candidates", self.depth_candidates, 2)
        if not (isinstance(self.depth_bound_fraction, (int, float)) and 0 < self.depth_bound_fraction <= 1):
            raise ValueError(f"depth_bound_fraction must be in (0, 1], got {self.depth_bound_fraction!r}")
        _positive_int("alternations", self.alternations, 0)
        _positive_int("polish_iterations", self.polish_iterations)
        _positive_int("translation_starts", self.translation_starts)
        _positive_int("motion_members", self.motion_members)
        _positive("members_agree_deg", self.members_agree_deg)
        _positive_int("iterations", self.iterations)
        _positive_int("coarse_iterations", self.coarse_iterations)
        _positive_int("start_iterations", self.start_iterations)
        _positive_int("min_cell_events", self.min_cell_events, 0)
        _positive_int("mask_isolated_us", self.mask_isolated_us, 0)
        _positive_int("min_neighbours", self.min_neighbours, 0)
        _positive_int("denoise_min_window_us", self.denoise_min_window_us, 0)
        if isinstance(self.denoise_min_rate_hz, bool) or not (isinstance(self.denoise_min_rate_hz, (int, float))
                                                                and 0 <= self.denoise_min_rate_hz < math.inf):
            raise ValueError("denoise_min_rate_hz must be a number >= 0 [Hz per pixel], "
                             f"got {self.denoise_min_rate_hz!r}")
        if isinstance(self.max_denoised_share, bool) or not (isinstance(self.max_denoised_share, (int, float))
                                                               and 0 < self.max_denoised_share <= 1):
            raise ValueError(f"max_denoised_share must lie in (0, 1], got {self.max_denoised_share!r}")
        check_filter(self.hot_pixels)
        for name, kind in (("patch_flow", PatchFlowSettings), ("refine", RefineSettings), ("sweep", SweepSettings),
                           ("quality", QualitySettings)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
