"""``cmax.fit``: depth and camera motion of one event window by contrast maximization.

The pieces (Gallego et al., CVPR 2018; the paper's section 4):

* the warp models of :mod:`cmax.warp` (flow, rotation, se3 + inverse-depth grid);
* the objectives of :mod:`cmax.objectives`: the multi-reference, normalised
  contrast for the motion, the per-cell local contrast plus total variation
  for the depth, the deformation guard against event collapse;
* a solver backend of :mod:`cmax.fitting.solvers` (scipy L-BFGS-B, casadi IPOPT, torch Adam);
* :mod:`cmax.fitting.stages`: the stages (rotation first, translation direction from
  several starts, depth by the plane sweep of :mod:`cmax.fitting.depth_sweep`, motion
  and depth alternated) and the coarse-to-fine driver;
* this module: the public :func:`fit`, its settings and the frozen
  :class:`FitResult`; :mod:`cmax.fitting.sequence` walks a recording.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace
import numpy as np
import torch

from cmax.camera import check_intrinsics
from cmax.events import Events
from cmax.geometry import se3_exp, se3_log
from cmax.fitting.stages import Window, fit_flow, fit_rotation, fit_se3
from cmax.iwe import accumulate_bilinear, blur
from cmax.fitting.solvers import Solver, make_solver
from cmax.warp import DepthGrid, WarpEvents, warp_flow, warp_rotation, warp_se3

__all__ = ["FitResult", "FitSettings", "LowParallaxWarning", "fit"]

LOW_PARALLAX_PX = 1.0
"""Below this median displacement [px] of the events by the translation over the window,
:func:`fit` warns (:class:`LowParallaxWarning`): on the held-out ``indoor_flying`` windows of
``benchmarks/accuracy_cmax.py`` the two with 0.33 and 0.67 px (speeds of 0.04 and 0.07 m/s) are
the two worst depths with the motion known (abs_rel 0.35 and 0.25)."""


class LowParallaxWarning(UserWarning):
    """The fitted translation barely moves the events over the window (``FitResult.parallax_px`` below
    ``LOW_PARALLAX_PX``): the depth, and without ``pose`` the translation direction, are poorly
    constrained. Filter it with ``warnings.simplefilter("ignore", LowParallaxWarning)``."""

MODELS = ("flow", "rotation", "se3")
#: The contrast of each model when ``FitSettings.contrast`` is None.
DEFAULT_CONTRAST = {"flow": "variance", "rotation": "gradient", "se3": "variance"}
#: Whether the motion contrast images each polarity apart when ``FitSettings.polarity_split`` is None.
DEFAULT_POLARITY_SPLIT = {"flow": False, "rotation": True, "se3": False}


@dataclass(frozen=True)
class FitSettings:
    """Options of :func:`fit` beyond the model (keyword arguments of ``fit`` override them).

    Attributes
    ----------
    contrast : {"variance", "gradient"} or None
        Contrast of the IWEs; None picks per model: ``"gradient"`` for
        ``rotation`` (on the tuning seeds 1-12 its omega error was 1.1% median,
        1.8% p90 against 1.5% / 3.9% with the variance), ``"variance"`` for
        ``flow`` and ``se3``.
    polarity_split : bool or None
        Image ON and OFF events apart in the motion contrast and add the two
        contrasts (an ON edge and the OFF edge that trails it no longer blur
        into one); None picks per model: True for ``rotation`` (tuning seeds
        1-12, four 30k-event subsets each: omega error 0.79% median, 1.61% p90
        against 0.99% / 2.19% merged), False for ``flow`` (endpoint error
        0.068 / 0.208 px split against 0.056 / 0.107 px merged, and twice the
        time) and ``se3`` (its motion comes from patch objectives, which image
        the polarities together).
    references : tuple of float
        Reference times of the multi-reference motion objective, as fractions
        of the window (0 = first event, 1 = last).
    sigma : float
        IWE blur [px].
    max_events : int
        Windows with more events are subsampled uniformly (seeded) to this many.
    depth_range : (float, float)
        Bounds of the depth [m] (in units of ``speed * 1 s`` when the scale is unknown).
        Give the scene's own range when it is known, as EMVS needs it: for se3
        without ``omega`` the far bound stops depths that run far to absorb
        a rotation error (held-out ``indoor_flying``: abs_rel 0.20 median with
        1-6.5 m, 0.34 with the default).
    depth_candidates : int
        Inverse depths of the plane sweep (uniform in inverse depth over
        ``depth_range``); the relative refinements recover the precision (36
        and 48 gave the same abs_rel on the tuning seeds, 1.65 s against 2.11 s).
    depth_smoothness : (float, float)
        Semi-global matching penalties ``(P1, P2)`` of the sweep (a step of
        one candidate, a larger jump between neighbouring grid nodes) in
        units of the median node confidence (:mod:`cmax.fitting.depth_sweep`).
        On the tuning seeds 1-12 with ``pose=`` (12 x 16 grid, one vote per
        event), abs_rel median / p90 0.107 / 0.126 with (0.1, 1.0), 0.105 /
        0.135 with (0.1, 0.5), 0.110 / 0.131 with (0.15, 1.5), against 0.112 /
        0.147 for the best 3 x 3 aggregation of neighbouring curves it
        replaced (weight 0.1); on windows with little parallax, whose curves
        are flat, it keeps nodes from running to the far bound.
    depth_coarsening : int
        The sweep over the whole ``depth_range`` runs on a grid this many
        times coarser than ``depth_grid``; the relative refinements run on
        ``depth_grid``. Tuning seeds, ``pose=``: 24 x 32 refined from 12 x 16,
        abs_rel median 0.099, against 0.107 for 12 x 16 alone and 0.101 for
        24 x 32 swept directly, at the same count of warps.
    depth_refinements : tuple of float
        Half-widths (log of a factor) of the relative sweeps that follow the first one.
    motion_init : {"patches", "starts"}
        Initial se3 motion: patch flows fitted to the motion-field equations,
        each patch weighted by the information matrix of its flow (the
        curvature of its contrast peak, so that a patch seeing one edge only
        constrains the flow across it; :mod:`cmax.fitting.patch_flow`), or a
        rotation fit then translation directions from several starts.
    motion_refinement : {"local", "none"}
        ``"local"``: the patch-flow motion is refined on the sum of per-patch
        normalised contrasts, each patch with its own depth
        (:func:`cmax.fitting.motion.refine_motion_local`, scipy L-BFGS-B
        whatever the ``solver``). On the tuning seeds 1-12 (three subsampling
        seeds) it took the direction error from 7.4 / 9.0 / 10.4 to
        6.9 / 8.3 / 9.8 deg median and omega RMS from 0.85-1.14 to 0.70-1.06
        deg/s, for about +0.7 s per window.
    zero_rotation_start : bool
        A second start of the ``"local"`` refinement: the motion-field fit of
        the patch flows with the rotation held at zero, then refined with the
        rotation free; the refined motion with the higher patch-wise contrast
        wins. For vehicles, whose rotation is small next to their forward
        speed: on the Prophesee drive the first start alone ends at a plane
        pitching at 134 deg/s, 74 deg from forward, and this one 2 deg from
        forward with a higher patch-wise contrast (the image's global
        contrast prefers the pitching plane). Off by default: on the tuning seeds
        1-12 it won on 2 windows (direction 6.5 -> 0.8 and 4.5 -> 6.0 deg) for
        about 1 s more per window (the se3 budget is 5 s); on the held-out
        windows it changed 4 of 20 (direction median 7.8 -> 8.3 deg).
    alternations : int
        Rounds of (motion with the depth held, depth sweep) after the first depth (se3 without pose).
    collapse_weight : float
        Weight of the deformation guard (:func:`cmax.objectives.deformation`).
    translation_starts : int
        Directions tried for the translation (6: +-x, +-y, +-z camera axes; 14 adds the diagonals).
    iterations : int
        Iteration limit of each solver stage.
    min_cell_events : int
        Depth cells with fewer events are outside the mask.
    seed : int
        Seed of the subsampling.
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
    motion_init: str = "patches"
    motion_refinement: str = "local"
    zero_rotation_start: bool = False
    collapse_weight: float = 0.1
    translation_starts: int = 6
    iterations: int = 60
    min_cell_events: int = 15
    seed: int = 0


@dataclass(frozen=True, eq=False)
class FitResult:
    """The motion (and depth) of one event window.

    Attributes
    ----------
    model : str
        ``"flow"``, ``"rotation"`` or ``"se3"``.
    t0_us, t1_us : int
        Times of the window's first and last events [µs].
    t_ref_us : int
        The reference time: the depth map is the scene's depth seen from the
        camera at this time, the IWEs are warped to it (the window's middle).
    flow : ndarray (2,) or None
        Optical flow [px/s] (model ``flow``).
    v, omega : ndarray (3,)
        Linear [m/s] and angular [rad/s] velocity, camera frame (``v`` is a unit
        vector times an unknown scale when ``scale_known`` is False; zero for
        ``flow``/``rotation``; ``omega`` is the given one when ``fit`` got ``omega=``).
    T : ndarray (4, 4)
        ``se3_exp((v, omega) (t1 - t0))``: the camera at ``t1`` in the frame of the camera at ``t0``.
    depth : ndarray (H, W) float32 or None
        z-depth [m] at ``t_ref_us``, dense (interpolated from the grid); see ``mask``.
    mask : ndarray (H, W) bool or None
        The event pixels of the reference view: pixels that hold at least one
        event once the events are warped to ``t_ref_us`` with the fitted
        motion and depth (:func:`event_pixels`), in cells with at least
        ``min_cell_events`` events. Like EMVS's semi-dense map, on the edges
        seen at ``t_ref_us``.
    inverse_depth_grid : ndarray (gh, gw) or None
        The optimised inverse depths [1/m] at the grid nodes.
    scale_known : bool
        Whether ``v`` and ``depth`` are metric (``speed`` or ``pose`` given).
    objective_before, objective_after : float
        Normalised multi-reference contrast (1 = unwarped events) of the start and the result.
    iterations, evaluations : int
    seconds : float
    message : str
        The last solver's message.
    success : bool
    iwe_before, iwe_after : ndarray (H, W) float32
        Event-count IWEs at ``t_ref_us`` without and with the fitted warp (blur sigma).
    events_used : int
    parallax_px : float or None
        se3: median over the events of how far the fitted translation alone
        moves each event over the whole window at its fitted depth [px]. The
        translation direction and the depth rest on this displacement: on the
        held-out benchmark windows the three with under 1.2 px of true
        parallax had direction errors of 20-101 deg, and this estimate flagged
        two of them (0.8 and 0.9 px). A wrong motion can also claim a large
        parallax: a small value is a warning, a large one no guarantee. None
        for ``flow`` and ``rotation``.
    depth_spread : ndarray (H, W) float32 or None
        se3: the range of log inverse depth over the 3 x 3 grid nodes around
        each pixel (:func:`depth_spread`): large at depth edges, where the
        bilinear grid blends two surfaces and most of the depth error lies; 0
        on a smooth surface. A per-pixel confidence for semi-dense use:
        ``mask & (depth_spread < limit)``; ``abs_rel_half`` in
        ``benchmarks/results/accuracy_cmax.md`` is the error on the half of the
        mask with the smallest spread. None for ``flow`` and ``rotation``.
    """

    model: str
    t0_us: int
    t1_us: int
    t_ref_us: int
    flow: np.ndarray | None
    v: np.ndarray
    omega: np.ndarray
    T: np.ndarray
    depth: np.ndarray | None
    mask: np.ndarray | None
    inverse_depth_grid: np.ndarray | None
    scale_known: bool
    objective_before: float
    objective_after: float
    iterations: int
    evaluations: int
    seconds: float
    message: str
    success: bool
    iwe_before: np.ndarray
    iwe_after: np.ndarray
    events_used: int
    parallax_px: float | None = None
    depth_spread: np.ndarray | None = None

    @property
    def twist(self) -> np.ndarray:
        """``(v, omega)`` (6,)."""
        return np.r_[self.v, self.omega]

    def plot(self, path) -> "object":
        """Write a PNG: IWE before, after, and the depth map (when fitted); returns the path."""
        from cmax import viz

        tiles = [viz.titled(viz.iwe_image(self.iwe_before), "IWE before"),
                 viz.titled(viz.iwe_image(self.iwe_after), "IWE after")]
        if self.depth is not None:
            depth = np.where(self.mask, self.depth, np.nan)
            tiles.append(viz.titled(viz.depth_image(depth), "depth" + ("" if self.scale_known else " (up to scale)")))
        return viz.save_png(path, viz.hstack(tiles))


# ----------------------------------------------------------------------------------------
# Validation and preparation
# ----------------------------------------------------------------------------------------
def _check_inputs(events: object, K: object, model: str) -> np.ndarray:
    if not isinstance(events, Events):
        raise TypeError(f"events must be cmax.Events, got {type(events).__name__}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    K = check_intrinsics(K)
    if abs(np.linalg.det(K)) < 1e-12:
        raise ValueError(f"K must be invertible, got {K.tolist()}")
    if len(events) < 10:
        raise ValueError(f"events: a window needs at least 10 events to fit a motion, got {len(events)}")
    if events.t[-1] == events.t[0]:
        raise ValueError("events all have the same timestamp: a window of zero duration shows no motion")
    return K


def _pose_twist(pose: object, duration_s: float) -> np.ndarray:
    """The constant twist of a known motion: a twist (6,) [m/s, rad/s], or T (4, 4) from t0 to t1."""
    array = np.asarray(pose, dtype=np.float64)
    if array.shape == (6,):
        xi = array
    elif array.shape == (4, 4):
        xi = se3_log(array) / duration_s
    else:
        raise ValueError(f"pose must be a twist (6,) [m/s, rad/s] or a (4, 4) motion over the window, got {array.shape}")
    if not np.isfinite(xi).all():
        raise ValueError("pose must be finite")
    return xi


def _known_omega(omega: object, pose: object) -> np.ndarray:
    """A known angular velocity (3,) [rad/s], checked."""
    if pose is not None:
        raise ValueError("give pose or omega, not both: pose already fixes the rotation")
    try:
        array = np.asarray(omega, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"omega must be 3 numbers [rad/s], got {omega!r}") from None
    if array.shape != (3,):
        raise ValueError(f"omega must be an angular velocity (3,) [rad/s], got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"omega must be finite, got {array.tolist()}")
    return array


# ----------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------
def fit(
    events: Events, K: object, model: str = "se3", *, speed: float | None = None, pose: object = None,
    omega: object = None, depth_grid: tuple[int, int] = (24, 32), solver: "str | Solver" = "scipy",
    init: FitResult | None = None,
    settings: FitSettings = FitSettings(), num_threads: int | None = 1, **options,
) -> FitResult:
    """Fit the motion (and the depth) of one window of events by contrast maximization.

    Parameters
    ----------
    events : Events
        One window (at least 10 events spanning a non-zero time). Both
        polarities are counted alike (the IWE counts events), so a window of
        one polarity is fine.
    K : array_like (3, 3)
        Pinhole intrinsics [px] of the (undistorted) events.
    model : {"se3", "rotation", "flow"}
        ``flow``: a constant optical flow [px/s]; ``rotation``: an angular
        velocity [rad/s]; ``se3``: linear and angular velocity plus an
        inverse-depth grid.
    speed : float, optional
        Known ``|v|`` [m/s] (se3): depth and ``v`` are metric.
    pose : array_like, optional
        Known motion of the window (se3): a twist ``(v, omega)`` (6,) [m/s,
        rad/s] or the (4, 4) transform from the camera at the first event to
        the camera at the last; only the depth is optimised.
    omega : array_like (3,), optional
        Known angular velocity [rad/s] of the window, camera frame (se3; e.g.
        a gyroscope's mean over the window, in the camera's axes): it is held
        and only the translation direction and the depth are fitted. The
        rotation is what limits the se3 depth: on the held-out benchmark
        windows (given the room's ``depth_range``) the depth has abs_rel 0.20
        median without ``omega``, 0.11 with the true rotation and 0.13 with a
        gyroscope 0.5 deg/s off on each axis; 0.34 without ``omega`` and with
        the default ``depth_range`` (``benchmarks/results/accuracy_cmax.md``).
    depth_grid : (rows, cols)
        Size of the inverse-depth grid (se3); the sweep over the whole depth
        range runs on a grid ``depth_coarsening`` times coarser (12 x 16 for
        the default 24 x 32), then refines on this one.
    solver : {"scipy", "casadi", "torch"} or cmax.fitting.solvers.Solver
    init : FitResult, optional
        Warm start (e.g. the previous window of a sequence).
    settings : FitSettings
        Further options; keyword arguments named like its fields override it
        (e.g. ``fit(..., contrast="gradient", max_events=20000)``).
    num_threads : int or None
        torch threads during the fit (restored afterwards); 1 is fastest on
        busy machines; None keeps the current setting.

    Returns
    -------
    FitResult
        With neither ``speed`` nor ``pose`` the translation and depth are up to
        one scale: ``|v| = 1`` and ``scale_known`` is False.

    Raises
    ------
    TypeError, ValueError
        Not an ``Events``; unknown model or solver; a bad K; fewer than 10
        events; all events at one time; ``speed`` not positive; a bad ``pose``
        or ``omega``; ``pose`` and ``omega`` together.

    Notes
    -----
    Stages for se3 (without ``pose``), by default: a constant flow per patch
    by contrast maximization, with the information matrix of each flow; the
    twist from the motion-field equations (information-weighted least squares
    over directions on the sphere, then in a cap around the best); the twist
    refined on the patch-wise contrast, each patch with its own depth
    (``motion_refinement="local"``; with ``zero_rotation_start`` also from
    the motion-field fit without rotation, the better of the two kept); the
    depth grid by a plane sweep of the contrast aggregated on the grid
    (:mod:`cmax.fitting.depth_sweep`); then
    ``alternations`` rounds of motion (depth held) and sweep. With
    ``motion_init="starts"`` the twist comes instead from a rotation-only fit
    and translation directions from several starts (normalised
    multi-reference contrast plus the deformation guard). With ``pose`` only
    the sweep runs. The depth belongs to ``t_ref_us`` (the window's middle),
    where the events are warped to.

    References
    ----------
    G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
    framework for event cameras", CVPR 2018, doi:10.1109/CVPR.2018.00407.
    S. Shiba, Y. Aoki, G. Gallego, "Event collapse in contrast maximization
    frameworks", Sensors 2022, doi:10.3390/s22145190.

    Examples
    --------
    >>> result = cmax.fit(events, K, model="rotation")       # doctest: +SKIP
    >>> result.omega                                          # doctest: +SKIP
    """
    start = time.perf_counter()
    K = _check_inputs(events, K, model)
    if options:
        unknown = set(options) - set(FitSettings.__dataclass_fields__)
        if unknown:
            raise TypeError(f"fit() got unexpected keyword arguments {sorted(unknown)}")
        settings = replace(settings, **options)
    if settings.contrast is None:
        settings = replace(settings, contrast=DEFAULT_CONTRAST[model])
    if settings.polarity_split is None:
        settings = replace(settings, polarity_split=DEFAULT_POLARITY_SPLIT[model])
    if not isinstance(settings.polarity_split, (bool, np.bool_)):
        raise TypeError(f"polarity_split must be True, False or None, got {settings.polarity_split!r}")
    near, far = (float(value) for value in settings.depth_range)
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"depth_range must satisfy 0 < near < far (metres), got {settings.depth_range}")
    if int(settings.max_events) < 10:
        raise ValueError(f"max_events must be >= 10, got {settings.max_events}")
    if not (isinstance(settings.depth_coarsening, (int, np.integer)) and settings.depth_coarsening >= 1):
        raise ValueError(f"depth_coarsening must be an integer >= 1, got {settings.depth_coarsening!r}")
    smoothness = np.asarray(settings.depth_smoothness, dtype=float).ravel()
    if smoothness.size != 2 or not np.all(np.isfinite(smoothness)) or np.any(smoothness < 0):
        raise ValueError(f"depth_smoothness must be two non-negative numbers (P1, P2), got {settings.depth_smoothness!r}")
    if settings.contrast not in ("variance", "gradient"):
        raise ValueError(f"contrast must be 'variance', 'gradient' or None, got {settings.contrast!r}")
    if settings.motion_init not in ("patches", "starts"):
        raise ValueError(f"motion_init must be 'patches' or 'starts', got {settings.motion_init!r}")
    if not isinstance(settings.zero_rotation_start, (bool, np.bool_)):
        raise TypeError(f"zero_rotation_start must be True or False, got {settings.zero_rotation_start!r}")
    if settings.motion_refinement not in ("local", "none"):
        raise ValueError(f"motion_refinement must be 'local' or 'none', got {settings.motion_refinement!r}")
    if speed is not None and not (np.isfinite(speed) and speed > 0):
        raise ValueError(f"speed must be a positive number of m/s, got {speed}")
    if (speed is not None or pose is not None or omega is not None) and model != "se3":
        raise ValueError(f"speed, pose and omega apply to model='se3', not {model!r}")
    known_omega = None if omega is None else _known_omega(omega, pose)
    if init is not None and not isinstance(init, FitResult):
        raise TypeError(f"init must be a FitResult, got {type(init).__name__}")
    backend = make_solver(solver)
    pose_xi = None if pose is None else _pose_twist(pose, (int(events.t[-1]) - int(events.t[0])) * 1e-6)
    previous_threads = torch.get_num_threads()
    if num_threads is not None:
        torch.set_num_threads(num_threads)
    try:
        w = Window.from_events(events, K, settings, backend, depth_grid)
        flow, v, omega, grid = None, np.zeros(3), np.zeros(3), None
        if model == "flow":
            flow = fit_flow(w, init.flow if init is not None and init.flow is not None else np.zeros(2))
        elif model == "rotation":
            omega = fit_rotation(w, init.omega if init is not None else np.zeros(3))
        else:
            scale = float(np.linalg.norm(pose_xi[:3])) if pose_xi is not None else (speed or 1.0)
            if scale <= 0:
                raise ValueError("pose has no translation: depth is unobservable under a pure rotation")
            v, omega, grid = fit_se3(w, speed=scale, pose_xi=pose_xi, init=init, omega=known_omega)
        result = _result(w, events, K, model, flow, v, omega, grid,
                         scale_known=pose is not None or speed is not None, seconds=time.perf_counter() - start)
    finally:
        torch.set_num_threads(previous_threads)
    if result.parallax_px is not None and result.parallax_px < LOW_PARALLAX_PX:
        unknown = "the depth is" if pose is not None else "the depth and the translation direction are"
        warnings.warn(f"cmax.fit: the translation moves the events by under {LOW_PARALLAX_PX:g} px over the window "
                      f"(FitResult.parallax_px): {unknown} poorly constrained; a longer window or a faster "
                      "motion gives more parallax", LowParallaxWarning, stacklevel=2)
    return result


def event_pixels(x: np.ndarray, y: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixels (H, W) bool that hold at least one of the points ``x, y`` (N,) [px] (rounded to the nearest
    pixel; points outside the image are left out).

    With the events warped to ``t_ref`` by the fitted motion and depth these are
    the event pixels *of the reference view*: where the window's edges are at
    ``t_ref``, the support of ``iwe_after``. The pixels the events were
    recorded at instead form the band each edge swept over the window, and at
    ``t_ref`` half of a moving depth edge's band shows the surface behind it
    (on the held-out ``indoor_flying`` windows of ``benchmarks/accuracy_cmax.py``,
    ``pose=``: abs_rel 0.098 on these pixels, 0.105 on the recorded event
    pixels, 0.110 on those dilated by 3 x 3, the mask before).
    """
    col, row = np.rint(x), np.rint(y)
    inside = (col >= 0) & (col <= width - 1) & (row >= 0) & (row <= height - 1)
    hits = np.zeros((height, width), bool)
    hits[row[inside].astype(np.intp), col[inside].astype(np.intp)] = True
    return hits


def _warp_with_grid(ev: WarpEvents, index: torch.Tensor, weight: torch.Tensor, dt: torch.Tensor, v, omega,
                    grid) -> tuple[torch.Tensor, torch.Tensor]:
    """se3 warp of the events ``ev`` by ``dt`` (N,) or (B, N) [s] with twist ``v, omega`` and each event's
    inverse depth interpolated from ``grid`` (gh, gw) [1/m] at its node ``index, weight`` (N, 4)."""
    dtype = ev.x.dtype
    rho = DepthGrid.sample(torch.as_tensor(grid, dtype=dtype), index, weight)
    return warp_se3(ev.rays, dt, torch.as_tensor(v, dtype=dtype), torch.as_tensor(omega, dtype=dtype), rho, ev.K)


def _warped(w: Window, flow, v, omega, grid, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The fit's events warped by ``dt`` (B, N) [s] with the fitted model (flow, rotation or se3)."""
    ev = w.ev
    with torch.no_grad():
        if flow is not None:
            return warp_flow(ev.x, ev.y, dt, torch.as_tensor(flow, dtype=ev.x.dtype))
        if grid is None:
            return warp_rotation(ev.rays, dt, torch.as_tensor(omega, dtype=ev.x.dtype), ev.K)
        return _warp_with_grid(ev, w.index, w.weight, dt, v, omega, grid)


def _all_events_at_reference(events: Events, K: np.ndarray, w: Window, v, omega, grid) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres of *all* the window's events (not the fit's subsample, not dithered) warped to ``t_ref``
    by the fitted se3 motion and depth grid: x, y (N,) [px]."""
    ev = WarpEvents.from_events(events, K, dither=False, dtype=torch.float64)
    index, weight = w.grid.weights(ev.x, ev.y)
    with torch.no_grad():
        x, y = _warp_with_grid(ev, index, weight, ev.dt((0.5,))[0], v, omega, grid)
    return x.numpy(), y.numpy()


def _objective(w: Window, flow, v, omega, grid) -> float:
    x, y = _warped(w, flow, v, omega, grid, w.dt)
    with torch.no_grad():
        return float(w.contrast(x, y, 1))


def _result(w: Window, events: Events, K: np.ndarray, model, flow, v, omega, grid, *, scale_known: bool, seconds: float
            ) -> FitResult:
    ev, s = w.ev, w.settings
    H, W = ev.height, ev.width
    with torch.no_grad():
        before = blur(accumulate_bilinear(ev.x, ev.y, None, H, W), s.sigma).numpy()
        x, y = _warped(w, flow, v, omega, grid, w.dt_mid)
        after = blur(accumulate_bilinear(x[0], y[0], None, H, W), s.sigma).numpy()
    depth = mask = None
    if grid is not None:
        depth = (1.0 / w.grid.upsample(grid)).astype(np.float32)
        counts = np.bincount(w.cell.numpy(), minlength=grid.size)
        supported = counts.reshape(grid.shape) >= s.min_cell_events
        cell_map = w.grid.cell_of(*[torch.from_numpy(a.ravel().astype(np.float64)) for a in np.mgrid[0:H, 0:W][::-1]])
        x_ref, y_ref = _all_events_at_reference(events, K, w, v, omega, grid)
        mask = event_pixels(x_ref, y_ref, H, W) & supported.ravel()[cell_map.numpy()].reshape(H, W)
    xi = np.r_[v, omega]
    parallax = None if grid is None else _parallax_px(w, np.asarray(v, float), np.asarray(grid, float))
    return FitResult(
        model=model, t0_us=ev.t0_us, t1_us=ev.t1_us, t_ref_us=ev.t0_us + (ev.t1_us - ev.t0_us) // 2,
        flow=None if flow is None else np.asarray(flow, float), v=np.asarray(v, float), omega=np.asarray(omega, float),
        T=se3_exp(xi * ev.duration_s), depth=depth, mask=mask,
        inverse_depth_grid=None if grid is None else np.asarray(grid, float), scale_known=scale_known,
        depth_spread=None if grid is None else depth_spread(np.asarray(grid, float), w.grid),
        objective_before=1.0, objective_after=_objective(w, flow, v, omega, grid),
        iterations=w.iterations, evaluations=w.evaluations, seconds=seconds, message=w.message,
        success=w.success, iwe_before=before, iwe_after=after, events_used=len(ev), parallax_px=parallax,
    )


def depth_spread(inverse_depth_grid: np.ndarray, grid: DepthGrid) -> np.ndarray:
    """Range of log inverse depth over the 3 x 3 nodes around each node of ``inverse_depth_grid`` (gh, gw)
    [1/m, > 0], interpolated to the pixels like the depth (:meth:`DepthGrid.upsample`): (H, W) float32, >= 0.

    ``log(rho_max / rho_min)`` of the neighbourhood: 0.69 next to a step from 2 m to 4 m, 0 on a
    constant depth. Nodes outside the grid repeat the edge (``mode="nearest"``).
    """
    from scipy.ndimage import maximum_filter, minimum_filter

    log_rho = np.log(np.asarray(inverse_depth_grid, dtype=np.float64).reshape(grid.shape))
    spread = maximum_filter(log_rho, size=3, mode="nearest") - minimum_filter(log_rho, size=3, mode="nearest")
    return grid.upsample(spread).astype(np.float32)


def _parallax_px(w: Window, v: np.ndarray, grid: np.ndarray) -> float:
    """Median displacement [px] of the events by the translation ``v T`` alone, at their fitted inverse depth."""
    ev = w.ev
    with torch.no_grad():
        x, y = _warp_with_grid(ev, w.index, w.weight, torch.full_like(ev.x, ev.duration_s), v, np.zeros(3), grid)
        return float(torch.hypot(x - ev.x, y - ev.y).median())
