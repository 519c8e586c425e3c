"""Settings of :func:`cmax.fit`: every tuned constant of the fit, in frozen dataclasses validated at construction.

:class:`FitSettings` holds the window-wide options and three nested sub-settings, one per se3 stage
that has constants of its own: :class:`PatchFlowSettings` (the patch-flow initialiser),
:class:`RefineSettings` (the patch-wise refinement) and :class:`SweepSettings` (the depth sweep's
second-level constants). Strategies are enums (:class:`MotionInit`, :class:`Refinement`); their string
values are accepted and turned into the enum. Why each default is what it is: ``docs/fitting.md``.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FitSettings", "MotionInit", "Refinement", "Polish", "PatchFlowSettings", "RefineSettings",
           "SweepSettings"]


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
        Uniform subsample of the window's events.
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
    """

    grid: tuple[int, int] = (4, 5)
    min_events: int = 200
    max_events: int = 20_000
    margin: float = 0.4
    sigmas: tuple[float | None, ...] = (3.0, None)
    iterations: int = 40
    coarse_step: int = 3
    directions: int = 3000
    cap_directions: int = 400

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


@dataclass(frozen=True)
class RefineSettings:
    """The patch-wise refinement of the se3 motion (:mod:`cmax.fitting.motion`).

    Attributes
    ----------
    grid : (rows, cols)
        Patches, each with its own inverse depth.
    min_events, max_events, margin
        As in :class:`PatchFlowSettings`.
    rho_candidates : int
        Inverse depths of the per-patch start sweep, log-uniform over ``depth_range``.
    iterations : int
        Solver iterations.
    """

    grid: tuple[int, int] = (6, 8)
    min_events: int = 100
    max_events: int = 20_000
    margin: float = 0.3
    rho_candidates: int = 24
    iterations: int = 60

    def __post_init__(self) -> None:
        object.__setattr__(self, "grid", _grid("refine.grid", self.grid))
        _positive_int("refine.min_events", self.min_events)
        _positive_int("refine.max_events", self.max_events)
        _fraction("refine.margin", self.margin)
        _positive_int("refine.rho_candidates", self.rho_candidates, 2)
        _positive_int("refine.iterations", self.iterations)


@dataclass(frozen=True)
class SweepSettings:
    """Second-level constants of the depth sweep (:mod:`cmax.fitting.depth_sweep`).

    Attributes
    ----------
    refine_candidates : int
        Steps of each relative sweep.
    chunk : int
        Candidates warped at once (memory against speed; no effect on the result).
    """

    refine_candidates: int = 13
    chunk: int = 8

    def __post_init__(self) -> None:
        _positive_int("sweep.refine_candidates", self.refine_candidates, 3)
        _positive_int("sweep.chunk", self.chunk)


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
    max_events : int
        Windows with more events are subsampled uniformly (seeded) to this many.
    depth_range : (float, float)
        Bounds of the depth [m] (in units of ``speed * 1 s`` when the scale is unknown); give the
        scene's own range when it is known.
    depth_candidates : int
        Inverse depths of the plane sweep (uniform in inverse depth over ``depth_range``).
    depth_smoothness : (float, float)
        Semi-global matching penalties ``(P1, P2)`` of the sweep, in units of the median node confidence.
    depth_coarsening : int
        The sweep over the whole range runs on a grid this many times coarser than ``depth_grid``.
    depth_refinements : tuple of float
        Half-widths (log of a factor) of the relative sweeps that follow the first one.
    motion_init : MotionInit or str
        ``"patches"`` (patch flows and the motion-field equations) or ``"starts"``.
    motion_refinement : Refinement or str
        ``"local"`` (the patch-wise contrast, each patch with its own depth) or ``"none"``.
    zero_rotation_start : bool
        A second start of the ``"local"`` refinement: the motion-field fit with the rotation held at
        zero (for vehicles); the refined motion with the higher patch-wise contrast wins.
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
    translation_starts : int
        Directions tried for the translation with ``motion_init="starts"`` (6: the camera axes; 14
        adds the diagonals).
    iterations : int
        Iteration limit of each solve of the global-contrast stages at full resolution.
    coarse_iterations : int
        Iteration limit of each solve at a coarser image scale.
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
    min_cell_events : int
        Depth cells with fewer events are outside the mask.
    seed : int
        Seed of the subsampling.
    patch_flow, refine, sweep
        The nested settings of those stages.
    """

    contrast: str | None = None
    polarity_split: bool | None = None
    references: tuple[float, ...] = (0.0, 0.5, 1.0)
    sigma: float = 1.0
    max_events: int = 60_000
    depth_range: tuple[float, float] = (0.5, 60.0)
    depth_candidates: int = 36
    depth_smoothness: tuple[float, float] = (0.1, 1.0)
    depth_coarsening: int = 2
    depth_refinements: tuple[float, ...] = (0.3, 0.1)
    alternations: int = 0
    motion_init: MotionInit = MotionInit.PATCHES
    motion_refinement: Refinement = Refinement.LOCAL
    zero_rotation_start: bool = False
    polish: Polish = Polish.NONE
    polish_iterations: int = 60
    collapse_weight: float = 0.1
    translation_starts: int = 6
    iterations: int = 60
    coarse_iterations: int = 20
    start_iterations: int = 25
    max_omega: float = 6.0
    max_flow_px: float = 2.0
    low_motion_px: float = 2.0
    min_cell_events: int = 15
    seed: int = 0
    patch_flow: PatchFlowSettings = field(default_factory=PatchFlowSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)
    sweep: SweepSettings = field(default_factory=SweepSettings)

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
        near, far = (float(value) for value in self.depth_range)
        if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
            raise ValueError(f"depth_range must satisfy 0 < near < far (metres), got {self.depth_range}")
        if not (isinstance(self.max_events, (int, np.integer)) and self.max_events >= 10):
            raise ValueError(f"max_events must be >= 10, got {self.max_events}")
        if not (isinstance(self.depth_coarsening, (int, np.integer)) and self.depth_coarsening >= 1):
            raise ValueError(f"depth_coarsening must be an integer >= 1, got {self.depth_coarsening!r}")
        smoothness = np.asarray(self.depth_smoothness, dtype=float).ravel()
        if smoothness.size != 2 or not np.all(np.isfinite(smoothness)) or np.any(smoothness < 0):
            raise ValueError(f"depth_smoothness must be two non-negative numbers (P1, P2), got "
                             f"{self.depth_smoothness!r}")
        if len(self.references) == 0 or any(not 0 <= r <= 1 for r in self.references):
            raise ValueError(f"references must be fractions of the window in [0, 1], got {self.references!r}")
        for name in ("sigma", "max_omega", "max_flow_px", "low_motion_px"):
            _positive(name, getattr(self, name))
        if not (np.isfinite(self.collapse_weight) and self.collapse_weight >= 0):
            raise ValueError(f"collapse_weight must be >= 0, got {self.collapse_weight!r}")
        _positive_int("depth_candidates", self.depth_candidates, 2)
        _positive_int("alternations", self.alternations, 0)
        _positive_int("polish_iterations", self.polish_iterations)
        _positive_int("translation_starts", self.translation_starts)
        _positive_int("iterations", self.iterations)
        _positive_int("coarse_iterations", self.coarse_iterations)
        _positive_int("start_iterations", self.start_iterations)
        _positive_int("min_cell_events", self.min_cell_events, 0)
        for name, kind in (("patch_flow", PatchFlowSettings), ("refine", RefineSettings), ("sweep", SweepSettings)):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
