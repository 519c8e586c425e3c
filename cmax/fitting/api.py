"""``cmax.fit``: depth and camera motion of one event window by contrast maximization.

The public :func:`fit`, its warnings and the frozen :class:`FitResult`. The fit itself is the
pipeline of :mod:`cmax.fitting.pipeline` (its stage order on one screen) over the frozen
:class:`~cmax.fitting.window.Window`, every stage solving through :mod:`cmax.fitting.solvers`;
the options are :class:`~cmax.fitting.settings.FitSettings`. Method details and the evidence behind
the defaults: ``docs/fitting.md``.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
import numpy as np
import torch

from cmax._threads import blas_threads_scope, torch_threads_scope
from cmax.camera import check_intrinsics, check_principal_point, intrinsics_oddity, pinhole_events, sensor_pixels
from cmax.contrast._warp_kernels import compiled_warp_applies, warp_se3_compiled
from cmax.events import Events, require_events
from cmax.hot_pixels import no_pixels, off_pixels
from cmax.geometry import se3_exp, se3_log
from cmax.fitting.pipeline import Motion, StageLog, depth_on_bounds, run_stages, stages_for
from cmax.fitting.quality import (NO_MOTION, LowMotion, LowMotionCause, Quality, Verdict, assess, bound_reason,
                                  motion_within_noise, rate_change, shuffled_gain_test, small_parallax_reason,
                                  isolated_events, neighbour_counts, noise_reason, noise_share, sparse_reason,
                                  best_turned, turned_reason, valley_reason, valley_turned, MotionScorer,
                                  _unsteady_reason,
                                  verdict_of, _isolated, _isolated_noise_share_and_sorted, _neighbour_counts,
                                  _Sorted, _sorted_subset)
from cmax.fitting.rotation_only import (fit_rotation_only, reports_rotation_only, rotation_only_reason,
                                        rotation_only_test)
from cmax.fitting.settings import FitSettings, QualitySettings, max_events_for
from cmax.fitting.solvers import Solver, make_solver
from cmax.fitting.window import SensorPixels, Window
from cmax.iwe import accumulate_bilinear, blur
from cmax.warp import DepthGrid, WarpEvents, warp_flow, warp_rotation, warp_se3

__all__ = ["FitResult", "FitSettings", "QualitySettings", "Verdict", "LowParallaxWarning", "LowMotionWarning",
           "BoundWarning", "fit"]


class LowParallaxWarning(UserWarning):
    """The fitted translation barely moves the events over the window (``FitResult.parallax_px`` below
    ``FitSettings.low_parallax_px``): the depth, and without ``pose`` the translation direction, are poorly
    constrained; or the fitted motion gains as much contrast on the events with their timestamps shuffled
    (``QualitySettings.shuffle_test``): nothing is measured; or (se3 with a free rotation) a rotation alone
    explains the events within noise (``QualitySettings.rotation_test``): the translation and depth are not
    measured, whatever ``parallax_px`` says (``omega`` is the rotation-only fit's when that scores at least as
    well as the se3 fit). Filter it with
    ``warnings.simplefilter("ignore", LowParallaxWarning)``."""


#: What a flow or rotation fit whose gain is within the noise of its spread over the image's cells may mean
#: (:attr:`~cmax.fitting.quality.LowMotionCause.CELL_NOISE`): the test cannot tell the two apart.
CELL_NOISE_ADVICE = ("either the motion is too small to measure (a longer window gives more) or parts of the image "
                     "move differently (depth differences, or a motion that changes within the window: model='se3', "
                     "a depth per part of the image, or a shorter window)")


class LowMotionWarning(UserWarning):
    """``flow``/``rotation``: the fitted motion moves the events by less than ``FitSettings.low_motion_px``
    over the window (``FitResult.motion_px``), its contrast gain is within noise, or no stage could improve
    on the start: the motion is too small to measure reliably (a longer window gives more motion) or, when
    the gain is within noise, parts of the image move differently (depth differences, or a motion that
    changes within the window: another model or a shorter window); or the same motion gains as much on the
    events with their timestamps shuffled: no motion is measured."""


class BoundWarning(UserWarning):
    """A motion parameter ended on its bound (``FitResult.stages[i].at_bound``; ``success`` is False):
    the true value is probably beyond it. Raise the bound (e.g. ``FitSettings.max_omega``). Also: at least
    ``FitSettings.depth_bound_fraction`` of the events' depth on an end of ``depth_range`` (``success`` False),
    or, with the motion fitted, at least ``QualitySettings.max_bound_share`` (the verdict ambiguous,
    ``quality.on_bound``)."""


MODELS = ("flow", "rotation", "se3")
#: The fewest events a window can be fitted with (fewer: a ValueError).
MIN_WINDOW_EVENTS = 10
#: The contrast of each model when ``FitSettings.contrast`` is None.
DEFAULT_CONTRAST = {"flow": "variance", "rotation": "gradient", "se3": "variance"}
#: Whether the motion contrast images each polarity apart when ``FitSettings.polarity_split`` is None.
DEFAULT_POLARITY_SPLIT = {"flow": False, "rotation": True, "se3": False}


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
        ``min_cell_events`` events; events without a neighbour within 1 px
        and ``FitSettings.mask_isolated_us`` (background-activity noise)
        leave no pixel of their own. Like EMVS's semi-dense map, on the
        edges seen at ``t_ref_us``.
    inverse_depth_grid : ndarray (gh, gw) or None
        The optimised inverse depths [1/m] at the grid nodes.
    scale_known : bool
        Whether ``v`` and ``depth`` are metric (``speed`` or ``pose`` given).
    objective_before, objective_after : float
        Normalised multi-reference contrast (1 = unwarped events) of the unwarped events and the result.
    iterations, evaluations : int
        Summed over the stages.
    seconds : float
    message : str
        The last stage's message, or the messages of the stages that failed.
    success : bool
        False when a stage failed: its solver ended worse than its start (the start was kept), or a
        parameter ended on a bound.
    iwe_before, iwe_after : ndarray (H, W) float32
        Event-count IWEs at ``t_ref_us`` without and with the fitted warp (blur sigma).
    events_used : int
        The events the fit used: the window's, without its hot pixels' (``hot_pixels``), without the events of
        too little neighbour support on a noisy se3 window (``FitSettings.min_neighbours``,
        ``denoise_min_rate_hz``), subsampled to ``FitSettings.max_events``.
    parallax_px : float or None
        se3: median over the events of how far the fitted translation alone
        moves each event over the whole window at its fitted depth [px]. The
        translation direction and the depth rest on this displacement
        (``docs/fitting.md``). A wrong motion can also claim a large
        parallax: a small value is a warning, a large one no guarantee (a
        rotation alone explaining the events, ``quality.cause``
        ``rotation_only``, says it is the fit's own). None for ``flow`` and
        ``rotation``.
    depth_spread : ndarray (H, W) float32 or None
        se3: the range of log inverse depth over the 3 x 3 grid nodes around
        each pixel (:func:`depth_spread`): large at depth edges, where the
        bilinear grid blends two surfaces and most of the depth error lies; 0
        on a smooth surface. A per-pixel confidence for semi-dense use:
        ``mask & (depth_spread < limit)``; ``abs_rel_half`` in
        ``benchmarks/results/accuracy_cmax.md`` is the error on the half of the
        mask with the smallest spread. None for ``flow`` and ``rotation``.
    stages : tuple of StageLog
        One per stage (:mod:`cmax.fitting.pipeline`): stage, objective before/after (the stage's own),
        iterations, evaluations, seconds, solver message, success, parameters on a bound.
    motion_px : float or None
        ``flow``/``rotation``: median displacement of the events by the fitted motion over the window [px].
    quality : Quality or None
        The verdict (ok / ambiguous / low parallax / failed), its reason and the scored alternative
        motions (:mod:`cmax.fitting.quality`, ``docs/quality.md``).
    hot_pixels : ndarray (K, 2) int64
        ``(x, y)`` of the hot pixels whose events the fit left out (``FitSettings.hot_pixels``,
        :class:`cmax.hot_pixels.HotPixelFilter`); empty when none.
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
    stages: tuple[StageLog, ...] = ()
    motion_px: float | None = None
    quality: Quality | None = None
    hot_pixels: np.ndarray = field(default_factory=no_pixels)

    @property
    def verdict(self) -> Verdict | None:
        """``quality.verdict``: ok, ambiguous, low_parallax or failed."""
        return None if self.quality is None else self.quality.verdict

    @property
    def twist(self) -> np.ndarray:
        """``(v, omega)`` (6,)."""
        return np.r_[self.v, self.omega]

    def image(self, *, depth_scale=None, zoom: int | None = None) -> np.ndarray:
        """The picture (BGR uint8, OpenCV's order: ``image[..., ::-1]`` for matplotlib): IWE before, after,
        and the depth map on the mask (when fitted) with a colour bar in metres; the verdict in the titles.

        ``depth_scale``: a :class:`cmax.viz.DepthScale` or ``(near, far)`` [m] shared by the pictures
        of a run (default: this map's own 1-99th percentiles). Pixels without an estimate are hatched
        grey, outside the colour map. ``zoom``: each pixel drawn as a ``zoom x zoom`` block (default
        :func:`cmax.viz.readable_zoom`: a small sensor's picture enlarged until its labels are readable).
        """
        from cmax import viz

        zoom = viz.readable_zoom(self.iwe_after.shape[1]) if zoom is None else zoom
        verdict = "" if self.verdict is None else f" ({self.verdict.value.replace('_', ' ')})"
        tiles = [viz.titled(viz.iwe_image(viz.enlarge(self.iwe_before, zoom)), "IWE before"),
                 viz.titled(viz.iwe_image(viz.enlarge(self.iwe_after, zoom)), f"IWE after{verdict}")]
        if self.depth is not None:
            depth = viz.enlarge(np.where(self.mask, self.depth, np.nan), zoom)
            label = "m" if self.scale_known else "up to scale"
            tiles.append(viz.depth_panel(depth, depth_scale, f"depth [{label}], t_ref {self.t_ref_us * 1e-6:.3f} s"
                                                             f"{verdict}", unit="m" if self.scale_known else ""))
        return viz.hstack(tiles)

    def plot(self, path, *, depth_scale=None, zoom: int | None = None) -> "object":
        """Write :meth:`image` (``depth_scale``, ``zoom`` as there) to ``path`` (.png, .jpg); returns the path."""
        from cmax import viz

        return viz.save_image(path, self.image(depth_scale=depth_scale, zoom=zoom))


# ----------------------------------------------------------------------------------------
# Validation and preparation
# ----------------------------------------------------------------------------------------
def _check_inputs(events: object, K: object, model: str) -> np.ndarray:
    require_events(events)
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    K = check_intrinsics(K)
    if abs(np.linalg.det(K)) < 1e-12:
        raise ValueError(f"K must be invertible, got {K.tolist()}")
    check_principal_point(K, events.width, events.height)
    if len(events) < MIN_WINDOW_EVENTS:
        raise ValueError(f"events: a window needs at least {MIN_WINDOW_EVENTS} events to fit a motion, got "
                         f"{len(events)}")
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


def _check_speed(speed: object) -> float | None:
    """A known speed [m/s] as one positive float (None stays None); arrays, strings and non-positive values
    are refused with the value in the message."""
    if speed is None:
        return None
    if np.ndim(speed) != 0 or isinstance(speed, (str, bytes, bool, np.bool_)):
        raise ValueError(f"speed must be one positive number of m/s, got {speed!r}")
    try:
        value = float(speed)
    except (TypeError, ValueError):
        raise ValueError(f"speed must be one positive number of m/s, got {speed!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"speed must be a positive number of m/s, got {speed}")
    return value


def _check_init(init: object) -> None:
    """A warm start: None or a :class:`FitResult` whose ``flow`` (2,) [px/s] (or None), ``v`` (3,) and ``omega``
    (3,) are finite numbers of those shapes (an edited or hand-made result of other shapes was broadcast or
    failed deep in the fit)."""
    if init is None:
        return
    if not isinstance(init, FitResult):
        raise TypeError(f"init must be a FitResult, got {type(init).__name__}")
    for name, shape, unit in (("flow", (2,), "px/s"), ("v", (3,), "m/s"), ("omega", (3,), "rad/s")):
        part = getattr(init, name)
        if part is None and name == "flow":
            continue
        try:
            array = np.asarray(part, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"init.{name} must be numbers of shape {shape}, got {part!r}") from None
        if array.shape != shape:
            raise ValueError(f"init.{name} must have shape {shape} [{unit}], got shape {array.shape}")
        if not np.isfinite(array).all():
            raise ValueError("init holds a non-finite motion (NaN or inf in v, omega or flow): it cannot start a fit")


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


def _warn_odd_intrinsics(K: np.ndarray, width: int, height: int) -> None:
    """Warn when a valid ``K`` is unlike any camera's (:func:`cmax.camera.intrinsics_oddity`): fitted as given."""
    oddity = intrinsics_oddity(K, width, height)
    if oddity is not None:
        warnings.warn(f"cmax.fit: {oddity}", UserWarning, stacklevel=3)


def _warn_fast_omega(omega: np.ndarray | None, max_omega: float) -> None:
    """Warn when a given angular velocity (``omega=``, or ``pose=``'s) [rad/s] turns faster than ``max_omega``,
    the bound of a fitted one: the usual cause is a gyroscope's deg/s passed as rad/s (57.3 times too fast),
    which the fit would take as given. Not refused: a fast spin is possible."""
    if omega is None or not np.linalg.norm(omega) > max_omega:
        return
    rate = float(np.linalg.norm(omega))
    warnings.warn(f"cmax.fit: the given rotation turns at {rate:.3g} rad/s ({np.degrees(rate):.4g} deg/s), faster "
                  f"than FitSettings.max_omega ({max_omega:g} rad/s, the bound of a fitted rotation): rotations are "
                  f"in rad/s, and a gyroscope's deg/s passed as rad/s is 57.3 times too fast ({np.radians(rate):.3g} "
                  "rad/s if these were deg/s)", UserWarning, stacklevel=3)


# ----------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------
def fit(
    events: Events, K: object, model: str = "se3", *, speed: float | None = None, pose: object = None,
    omega: object = None, depth_grid: tuple[int, int] = (24, 32), solver: "str | Solver" = "scipy",
    init: FitResult | None = None,
    settings: FitSettings | None = None, num_threads: int | None = 1,
    **options,
) -> FitResult:
    """Fit the motion (and the depth) of one window of events by contrast maximization.

    Parameters
    ----------
    events : Events
        One window (at least 10 events spanning a non-zero time). Both
        polarities are counted alike (the IWE counts events), so a window of
        one polarity is fine.
    K : array_like (3, 3) or cmax.Camera
        Pinhole intrinsics [px] of the (undistorted) events; or the
        :class:`cmax.Camera` of the events' sensor, whose distortion (and
        rectification, if any) is undone, as ``cmax fit --calib`` does: the
        warp takes each event dithered over its sensor pixel and mapped
        through the lens, unrounded (:meth:`cmax.Camera.undistort_points`),
        the masks and pixel tests its nearest undistorted pixel
        (:meth:`cmax.Camera.undistort_events`; events that land outside are
        dropped), so that the depth and masks are maps of the undistorted
        image.
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
        and only the translation direction and the depth are fitted (the
        rotation is what limits the se3 depth: ``docs/fitting.md``).
    depth_grid : (rows, cols)
        Size of the inverse-depth grid (se3); the sweep over the whole depth
        range runs on a grid ``depth_coarsening`` times coarser (12 x 16 for
        the default 24 x 32), then refines on this one.
    solver : {"scipy", "casadi", "torch"} or cmax.fitting.solvers.Solver
    init : FitResult, optional
        Warm start (e.g. the previous window of a sequence): ``flow`` and
        ``rotation`` start from its flow or omega; se3 tries its translation
        direction (and omega) as one more start of the motion refinement (or
        of the translation starts), the best one winning. With ``pose`` only
        the depth is fitted, by a sweep over the whole range that needs no
        start, and with ``motion_refinement="none"`` no objective compares
        starts: there ``init`` is checked but not used.
    settings : FitSettings, optional
        Further options, among them ``settings.quality`` (:class:`QualitySettings`: the ambiguity test
        and the low-motion test behind ``FitResult.quality``, :mod:`cmax.fitting.quality`).
    **options
        Alternatively, fields of :class:`FitSettings` as keywords (e.g.
        ``fit(..., depth_range=(1.0, 6.5))``, the scene's depth range [m], near and far: the one that
        matters most for se3, where the depth sweep and the bound rules use it; ``fit(..., contrast="gradient",
        max_events=20000)`` or
        ``fit(..., quality=QualitySettings(ambiguity_test=False))``); not together with ``settings``
        (a TypeError: no keyword silently overrides a field of ``settings``).
    num_threads : int or None
        torch threads during the fit (restored afterwards); 1 is fastest on
        busy machines; None lets :func:`cmax._threads.torch_threads` choose
        from the window's size, the cores and the machine's load.

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
        or ``omega``; ``pose`` and ``omega`` together; ``pose`` and a ``speed``
        other than its own; ``settings`` and
        keyword options together.

    Warns
    -----
    LowParallaxWarning
        se3: the translation moves the events by under ``FitSettings.low_parallax_px``, or the fitted (or
        given) motion gains as much contrast on the events with their timestamps shuffled
        (``QualitySettings.shuffle_test``, :func:`cmax.fitting.quality.shuffled_gain_test`: noise), or, with the
        rotation free, a rotation alone explains the events within noise (``QualitySettings.rotation_test``,
        :func:`cmax.fitting.rotation_only.rotation_only_test`: a camera that only turns or hovers); ``omega`` is
        then the rotation-only fit's when that scores at least as well as the se3 fit (the se3 fit's own motion
        in ``quality.replaced``), else the se3 fit's.
    LowMotionWarning
        flow, rotation: the motion moves the events by under ``low_motion_px``, its contrast gain is
        within noise (``QualitySettings.motion_test``, :func:`cmax.fitting.quality.motion_within_noise`)
        or matched on time-shuffled events (``shuffle_test``), or no stage improved on the start.
    BoundWarning
        A motion parameter ended on its bound (``success`` is False).

    Notes
    -----
    The stages of each model are listed, in order, in :func:`cmax.fitting.pipeline.stages_for`;
    each one's log is in ``FitResult.stages``. The depth belongs to ``t_ref_us`` (the window's
    middle), where the events are warped to.

    References
    ----------
    G. Gallego, H. Rebecq, D. Scaramuzza, "A unifying contrast maximization
    framework for event cameras", CVPR 2018, doi:10.1109/CVPR.2018.00407.
    S. Shiba, Y. Aoki, G. Gallego, "Event collapse in contrast maximization
    frameworks", Sensors 2022, doi:10.3390/s22145190.

    Examples
    --------
    Events of 300 points moving at (40, -20) px/s for 0.1 s, and the flow ``fit`` finds:

    >>> import numpy as np, cmax
    >>> rng = np.random.default_rng(0)
    >>> x0, y0 = rng.uniform(5, 50, 300), rng.uniform(5, 43, 300)           # the points [px]
    >>> t_s = np.sort(rng.uniform(0, 0.1, 6000)); point = rng.integers(0, 300, 6000)
    >>> events = cmax.Events(np.rint(x0[point] + 40 * t_s), np.rint(y0[point] - 20 * t_s),
    ...                      np.rint(t_s * 1e6).astype(np.int64), np.ones(6000), width=64, height=48)
    >>> K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]])
    >>> result = cmax.fit(events, K, model="flow")
    >>> result.flow.round(), result.success
    (array([ 40., -20.]), True)
    """
    start = time.perf_counter()
    sensor = _sensor_pixels(events, K)
    events, K = pinhole_events(events, K)
    K = _check_inputs(events, K, model)
    _warn_odd_intrinsics(K, events.width, events.height)
    settings = _settings(settings, options, model)
    settings = replace(settings, max_events=max_events_for(settings.max_events, events.width, events.height))
    unfiltered = events
    events, hot = _without_hot_pixels(events, settings)
    if sensor is not None and events is not unfiltered:
        sensor = replace(sensor, pixels=sensor.pixels[off_pixels(unfiltered, hot)])
    speed = _check_speed(speed)
    if (speed is not None or pose is not None or omega is not None) and model != "se3":
        raise ValueError(f"speed, pose and omega apply to model='se3', not {model!r}")
    known_omega = None if omega is None else _known_omega(omega, pose)
    _check_init(init)
    backend = make_solver(solver)
    pose_xi = None if pose is None else _pose_twist(pose, (int(events.t[-1]) - int(events.t[0])) * 1e-6)
    scale = float(np.linalg.norm(pose_xi[:3])) if pose_xi is not None else (speed or 1.0)
    if pose_xi is not None and speed is not None and not np.isclose(speed, scale, rtol=1e-6, atol=0.0):
        raise ValueError(f"pose moves at {scale:.6g} m/s but speed={speed:.6g} m/s: give one of them "
                         "(pose already fixes the speed)")
    _warn_fast_omega(known_omega if pose_xi is None else pose_xi[3:], settings.max_omega)
    if model == "se3" and scale <= 0:
        raise ValueError("pose has no translation: depth is unobservable under a pure rotation")
    with torch_threads_scope(len(events), threads=num_threads) as threads, blas_threads_scope(threads):
        shared_test = model == "se3" and settings.mask_isolated_us == settings.quality.noise_window_us
        if shared_test:     # the mask's and the noise's test and the neighbour filter, the events sorted once for all
            isolated, noise, ordered = _isolated_noise_share_and_sorted(events.x, events.y, events.t, events.width,
                                                                        events.height, settings.mask_isolated_us)
        else:
            isolated = ordered = None
            noise = (noise_share(events.x, events.y, events.t, events.width, events.height,
                                 settings.quality.noise_window_us, max_queries=settings.max_events)
                     if model == "se3" else None)
        fitted, keep = (events, None) if noise is None else _without_weak_events(events, noise, settings, ordered)
        if sensor is not None and keep is not None:
            sensor = replace(sensor, pixels=sensor.pixels[keep])
        w = Window.from_events(fitted, K, settings, depth_grid, sensor)
        motion = _start(model, init, pose_xi, known_omega, scale)
        stages = stages_for(model, w, pose_known=pose_xi is not None, hold_omega=known_omega is not None,
                            warm_v=init.v if init is not None and model == "se3" else None)
        motion, logs = run_stages(stages, w, motion, backend)
        if known_omega is not None:
            motion = replace(motion, omega=known_omega)
        warped = _warped(w, motion, w.dt)     # the objective's, the cell tests' and the rotation-only test's
        result = _result(w, fitted, K, model, motion, logs, scale_known=pose is not None or speed is not None,
                         isolated=_fitted_isolated(isolated, keep, ordered, events, settings),
                         seconds=time.perf_counter() - start, warped=warped)
        low = _low_motion(w, result, motion, pose_known=pose_xi is not None, warped=warped)
        own = None
        if low is None and model == "se3" and pose_xi is None and known_omega is None and result.success and \
                settings.quality.rotation_test:
            result, low, own = _rotation_only(w, result, motion, backend, warped)
        rate = rate_change(events.t) if model == "se3" and pose_xi is None else None
        on_bound = _on_bound(w, result, low, pose_known=pose is not None)
        quality = _quality(w, result, low, backend, pose_known=pose is not None, hold_omega=known_omega is not None,
                           speed=scale, given=len(fitted), rate=rate, on_bound=on_bound, noise=noise)
        result = replace(result, quality=quality if own is None else replace(quality, replaced=own),
                         hot_pixels=hot, seconds=time.perf_counter() - start)
    _warn(result, settings, low, pose is not None, on_bound)
    return result


def _settings(settings: FitSettings | None, options: dict, model: str) -> FitSettings:
    """The settings of one fit: ``settings`` or the keyword ``options`` (not both), with the per-model
    contrast and polarity split resolved."""
    if settings is not None and options:
        raise TypeError(f"fit() takes settings= or keyword options, not both (got settings and {sorted(options)})")
    if settings is not None and not isinstance(settings, FitSettings):
        raise TypeError(f"settings must be a FitSettings, got {type(settings).__name__}")
    if options:
        unknown = set(options) - set(FitSettings.__dataclass_fields__)
        if unknown:
            raise TypeError(f"fit() got unexpected keyword arguments {sorted(unknown)}")
    settings = settings if settings is not None else FitSettings(**options)
    if settings.contrast is None:
        settings = replace(settings, contrast=DEFAULT_CONTRAST[model])
    if settings.polarity_split is None:
        settings = replace(settings, polarity_split=DEFAULT_POLARITY_SPLIT[model])
    return settings


def _sensor_pixels(events: Events, K: object) -> SensorPixels | None:
    """For a ``K`` that is a :class:`cmax.Camera` with a lens (not :attr:`~cmax.Camera.is_pinhole`): the sensor
    pixels (M, 2) of the events its :meth:`~cmax.Camera.undistort_events` keeps, in their order, and the camera;
    None otherwise (the events' checks are :func:`cmax.camera.pinhole_events`'s)."""
    pixels = sensor_pixels(events, K)
    return None if pixels is None else SensorPixels(pixels, K)


def _without_hot_pixels(events: Events, settings: FitSettings) -> tuple[Events, np.ndarray]:
    """``events`` without the events of their hot pixels (``settings.hot_pixels``, None: all kept) and
    those pixels (K, 2) ``(x, y)``; refused when too few events remain to fit."""
    if settings.hot_pixels is None:
        return events, no_pixels()
    kept, hot = settings.hot_pixels.apply(events)
    if not len(hot):
        return events, hot
    if len(kept) < MIN_WINDOW_EVENTS or kept.t[-1] == kept.t[0]:
        span = int(kept.t[-1] - kept.t[0]) if len(kept) else 0
        raise ValueError(f"events: without the {len(events) - len(kept):,} events of its {len(hot)} hot pixel(s) the "
                         f"window holds {len(kept)} events over {span} µs: too few to fit a motion "
                         "(hot_pixels=None keeps every event)")
    return kept, hot


def _noise_rate_hz(events: Events, share: float) -> float:
    """The background-activity rate [Hz per pixel] of a window whose events are an estimated ``share`` of noise
    (:func:`cmax.fitting.quality.noise_share`): that share of its events over its pixels and duration (0 for a
    window of one time stamp)."""
    duration_s = (int(events.t[-1]) - int(events.t[0])) * 1e-6
    return share * len(events) / (events.width * events.height * duration_s) if duration_s > 0 else 0.0


def _without_weak_events(events: Events, share: float, settings: FitSettings,
                         ordered: _Sorted | None = None) -> tuple[Events, np.ndarray | None]:
    """``(fitted, keep)``: ``events`` without those of too little neighbour support to be the scene's (``keep``
    (N,) bool: the events left; None when all are): fewer than
    ``settings.min_neighbours`` other events within 1 px and ``settings.mask_isolated_us`` µs
    (:func:`cmax.fitting.quality.neighbour_counts`; background-activity noise next to the scene has one at most,
    mostly), when the window's estimated noise rate [Hz per pixel] (:func:`_noise_rate_hz` of its estimated noise
    ``share``, :func:`cmax.fitting.quality.noise_share`) is at least ``settings.denoise_min_rate_hz`` (below it
    nothing is counted). ``events`` itself when the filter is off (either setting 0), below that rate, on a window
    shorter than ``settings.denoise_min_window_us`` (whose scene's own events lie alone too often), when the
    estimated ``share`` or the share the filter would leave out is over ``settings.max_denoised_share`` (a window
    of mostly noise, or too sparse: its verdict says so; the few noise events that have neighbours would be kept
    and read as a scene), or when fewer than ``MIN_WINDOW_EVENTS`` over more than one time stamp would remain.
    ``ordered``: the events already sorted by pixel and time with ``settings.mask_isolated_us``
    (:func:`cmax.fitting.quality._isolated_noise_share_and_sorted`), counted on instead of sorting them again."""
    if not (settings.min_neighbours and settings.mask_isolated_us) or share > settings.max_denoised_share or \
            int(events.t[-1]) - int(events.t[0]) < settings.denoise_min_window_us or \
            _noise_rate_hz(events, share) < settings.denoise_min_rate_hz:
        return events, None
    support = (neighbour_counts(events.x, events.y, events.t, events.width, events.height, settings.mask_isolated_us)
               if ordered is None else _neighbour_counts(ordered, events.width, events.height,
                                                         settings.mask_isolated_us, 1))
    keep = support >= settings.min_neighbours
    kept = int(np.count_nonzero(keep))
    if kept == len(events) or len(events) - kept > settings.max_denoised_share * len(events) or \
            kept < MIN_WINDOW_EVENTS or events.t[keep][-1] == events.t[keep][0]:
        return events, None
    return Events(events.x[keep], events.y[keep], events.t[keep], events.p[keep], events.width, events.height,
                  time_unit="us"), keep


def _fitted_isolated(isolated: np.ndarray | None, keep: np.ndarray | None, ordered: _Sorted | None,
                     events: Events, settings: FitSettings) -> np.ndarray | None:
    """The isolation test (:func:`cmax.fitting.quality.isolated_events`, ``settings.mask_isolated_us``, 1 px) of the
    fitted events, (M,) bool, from what the fit has of the window ``events``: its flags ``isolated`` (N,) when
    nothing was left out (``keep`` None), else those of the subset ``keep`` (N,) bool on the window's sort
    ``ordered`` (:func:`cmax.fitting.quality._sorted_subset`: not sorted again); None when neither is at hand (the
    depth mask then tests the fitted events itself)."""
    if keep is None:
        return isolated
    if ordered is None:
        return None
    return _isolated(_sorted_subset(ordered, keep), events.width, events.height, settings.mask_isolated_us, 1)


def _start(model: str, init: "FitResult | None", pose_xi: np.ndarray | None, known_omega: np.ndarray | None,
           scale: float) -> Motion:
    """The motion the stages start from: the known pose, or the warm start's flow / omega, else zero."""
    if pose_xi is not None:
        return Motion(v=pose_xi[:3], omega=pose_xi[3:], speed=scale)
    flow = init.flow if model == "flow" and init is not None and init.flow is not None else None
    omega = init.omega if init is not None and model != "flow" else np.zeros(3)
    if known_omega is not None:
        omega = known_omega
    return Motion(flow=None if flow is None else np.asarray(flow, float), omega=np.asarray(omega, float),
                  speed=scale)


def _low_motion(w: Window, result: FitResult, motion: Motion, *, pose_known: bool = False,
                warped: tuple[torch.Tensor, torch.Tensor] | None = None) -> LowMotion | None:
    """Why the fit moved the events too little to trust (the rule of the low-parallax and low-motion
    warnings and of the ``low_parallax`` verdict; :class:`~cmax.fitting.quality.LowMotionCause` names it), or
    None: se3 parallax under ``low_parallax_px``; flow/rotation motion under ``low_motion_px``, or
    (``quality.motion_test``) a contrast gain within the noise of its spread over the image's cells
    (:func:`cmax.fitting.quality.motion_within_noise`); every model, with a given pose too
    (``quality.shuffle_test``): a gain that the time-shuffled events share
    (:func:`cmax.fitting.quality.shuffled_gain_test`); ``pose_known`` words the reason for it. ``warped``: the
    events warped by ``motion`` to the reference times of ``w.dt``, ``x, y`` (B, N) [px], when the caller has them
    (:func:`_warped`; None: warped here)."""
    settings = w.settings
    if result.parallax_px is not None and result.parallax_px < settings.low_parallax_px:
        return LowMotion(LowMotionCause.PARALLAX,
                         f"parallax {result.parallax_px:.2f} px, under low_parallax_px={settings.low_parallax_px:g}")
    if result.motion_px is not None and result.motion_px < settings.low_motion_px:
        return LowMotion(LowMotionCause.MOTION,
                         f"motion {result.motion_px:.2f} px, under low_motion_px={settings.low_motion_px:g}")
    quality = settings.quality
    if not (quality.motion_test and result.motion_px is not None) and not quality.shuffle_test:
        return None
    x, y = _warped(w, motion, w.dt) if warped is None else warped
    if quality.motion_test and result.motion_px is not None:
        gain, noise, within = motion_within_noise(w, x, y, quality)
        if within:
            return LowMotion(LowMotionCause.CELL_NOISE,
                             f"the {result.model}'s contrast gain {gain:.3g} is within the noise of its spread over "
                             f"the image's cells ({noise:.3g}): the fitted {result.motion_px:.2f} px of motion are "
                             "not measured (they sharpen only parts of the image)")
    if quality.shuffle_test:
        order = torch.randperm(w.dt.shape[1], generator=torch.Generator().manual_seed(settings.seed))
        xs, ys = _warped(w, motion, w.dt[:, order])
        gain, shuffled, flagged = shuffled_gain_test(w, x, y, xs, ys, quality)
        what = "the given motion and the swept depth" if pose_known else f"the {result.model}"
        if flagged and gain <= 0:
            return LowMotion(LowMotionCause.NO_MOTION,
                             f"{what} do{'' if pose_known else 'es'} not sharpen the image of warped events (contrast "
                             f"gain {gain:.3g} over the unwarped events): {NO_MOTION}")
        if flagged:
            return LowMotion(LowMotionCause.NO_MOTION,
                             f"the contrast gain {gain:.3g} of {what} is matched on the events with their timestamps "
                             f"shuffled ({shuffled:.3g}, >= {quality.shuffle_fraction:g} of it): it comes from the "
                             f"image's border, not from aligning events; {NO_MOTION}")
    return None


def _rotation_only(w: Window, result: FitResult, motion: Motion, solver: Solver,
                   warped: tuple[torch.Tensor, torch.Tensor] | None = None
                   ) -> tuple[FitResult, LowMotion | None, tuple[np.ndarray, np.ndarray] | None]:
    """The model-selection test of a se3 fit with a free rotation
    (:func:`cmax.fitting.rotation_only.rotation_only_test`): when a rotation alone explains the window's events
    within noise, the ``low_parallax`` rule (:attr:`~cmax.fitting.quality.LowMotionCause.ROTATION_ONLY`), and, when
    the rotation-only fit scores at least as well (:func:`cmax.fitting.rotation_only.reports_rotation_only`), the
    result with its ``omega`` (and ``T``) and the se3 fit's own ``(v, omega)``, else the result as it is and None;
    when not, the result as it is, None and None. ``warped``: the events warped by ``motion`` to the reference times
    of ``w.dt``, ``x, y`` (B, N) [px], when the caller has them (:func:`_warped`; None: warped here)."""
    quality = w.settings.quality
    x, y = _warped(w, motion, w.dt) if warped is None else warped
    omega = fit_rotation_only(w, result.v, result.omega, _events_rho(w, motion.inverse_depth), solver,
                              quality.shuffle_events)
    test = rotation_only_test(w, x, y, omega, quality)
    if not test.within_noise:
        return result, None, None
    low = LowMotion(LowMotionCause.ROTATION_ONLY, rotation_only_reason(test, result.parallax_px))
    if not reports_rotation_only(test):
        return result, low, None
    own = (result.v.copy(), result.omega.copy())
    return replace(result, omega=test.omega, T=se3_exp(np.r_[result.v, test.omega] * w.ev.duration_s)), low, own


def _on_bound(w: Window, result: FitResult, low: LowMotion | None, pose_known: bool) -> str:
    """Why too much of a fitted se3 motion's depth lies on an end of ``depth_range``
    (:func:`cmax.fitting.quality.bound_reason`), "" when it does not, or when the pose is given, the fit failed
    or its motion is too small to trust (their own verdicts then)."""
    if result.model != "se3" or pose_known or not result.success or low is not None:
        return ""
    near, far = w.settings.depth_range
    shares = depth_on_bounds(result.inverse_depth_grid.reshape(-1), w.index, w.weight, (1.0 / far, 1.0 / near),
                             w.settings.depth_candidates)
    return bound_reason(shares, (near, far), w.settings.quality.max_bound_share)


def _quality(w: Window, result: FitResult, low: LowMotion | None, solver: Solver, *, pose_known: bool,
             hold_omega: bool, speed: float, given: int, rate: float | None = None, on_bound: str = "",
             noise: float | None = None) -> Quality:
    """The verdict of a finished fit (:class:`QualitySettings` ``w.settings.quality``) with the low-motion
    rule that fired, ``low`` (:func:`_low_motion`), the window's :func:`cmax.fitting.quality.rate_change`
    ``rate`` (None: not measured) and :func:`_on_bound`'s reason; the ambiguity test (:func:`cmax.fitting.quality.assess`) runs on se3 fits
    with a fitted direction that did not fail and have parallax, and so do the rules of sparse windows
    (:func:`cmax.fitting.quality.sparse_reason`; ``given``: the events of the window before subsampling) and of
    small parallax with the rotation free (:func:`cmax.fitting.quality.small_parallax_reason`); ``noise``: the
    window's :func:`cmax.fitting.quality.noise_share` (None: not measured), judged by
    :func:`cmax.fitting.quality.noise_reason`."""
    quality = w.settings.quality
    failed = [log.stage for log in result.stages if not log.success]
    alternatives, note = (), ("ambiguity not tested: the pose is given" if pose_known else
                              "ambiguity not tested: a model without translation" if result.model != "se3" else
                              "ambiguity not tested (QualitySettings.ambiguity_test False)")
    tested, sparse, small, turned, flat = True, "", "", "", ""
    noisy = "" if noise is None else noise_reason(noise, quality.max_noise_share, quality.noise_window_us)
    if result.model == "se3" and not pose_known and quality.ambiguity_test and result.success and low is None:
        scorer = MotionScorer.build(w, result.v, result.omega, speed, quality)
        alternatives, note, tested = assess(w, result.v, result.omega, speed, quality, solver, hold_omega=hold_omega,
                                            scorer=scorer)
        sparse = sparse_reason(result.events_used, given, w.ev.width, w.ev.height, quality.min_event_density,
                               quality.min_event_density_area)
        small = "" if hold_omega else small_parallax_reason(result.parallax_px, quality.min_ok_parallax_px,
                                                            (w.ev.width, w.ev.height), quality.min_ok_parallax_area)
        # the turn can only make an ok ambiguous: not run where another rule already keeps the window from ok
        decided = on_bound or sparse or small or noisy or (rate is not None and
                                                            _unsteady_reason(rate, quality.max_rate_change))
        turned = _turned(w, result, speed, quality, alternatives, tested and not hold_omega and not decided, scorer)
        flat = _flat_valley(w, result, speed, quality, alternatives,
                            tested and not hold_omega and not (turned or decided), scorer)
    return verdict_of(success=result.success, failed_stages=failed, low_motion=low, alternatives=alternatives,
                      note=note, untestable=not tested, rate=rate, max_rate_change=quality.max_rate_change,
                      sparse=sparse, on_bound=on_bound, small_parallax=small, noise_share=noise, noisy=noisy,
                      turned=turned, flat_valley=flat)


def _turned(w: Window, result: FitResult, speed: float, quality: QualitySettings, alternatives: tuple,
            due: bool, scorer: MotionScorer | None = None) -> str:
    """:func:`cmax.fitting.quality.turned_reason` of a se3 fit whose ambiguity test found every alternative worse
    beyond noise (``alternatives``; ``due``: tested, with the rotation free, and no other rule keeps the window from
    ``ok``), "" otherwise: the test is only run where it can change the verdict, an ``ok`` into ``ambiguous``.
    ``scorer``: the ambiguity test's :class:`cmax.fitting.quality.MotionScorer` of the fit, scored on again (None:
    built anew)."""
    if not due or not alternatives or any(a.within_noise for a in alternatives):
        return ""
    turned = best_turned(w, result.v, result.omega, speed, quality, scorer)
    return turned_reason(turned, quality.bas_relief_turn_deg)


def _flat_valley(w: Window, result: FitResult, speed: float, quality: QualitySettings, alternatives: tuple,
                 due: bool, scorer: MotionScorer | None = None) -> str:
    """:func:`cmax.fitting.quality.valley_reason` of a se3 fit whose ambiguity test found every alternative worse
    beyond noise (``alternatives``; ``due``: tested, with the rotation free, and no other rule already keeping the
    window from ``ok``), "" otherwise: the test is only run where it can change the verdict. ``scorer``: the
    ambiguity test's :class:`cmax.fitting.quality.MotionScorer` of the fit (None: built anew)."""
    if not due or not alternatives or any(a.within_noise for a in alternatives):
        return ""
    turned = valley_turned(w, result.v, result.omega, speed, quality, scorer)
    return valley_reason(turned, quality.bas_relief_valley_deg)


def _warn(result: FitResult, settings: FitSettings, low: LowMotion | None, pose_known: bool,
          on_bound: str = "") -> None:
    """The warnings of a finished fit: low parallax (se3), low motion (flow, rotation), bounds. ``low`` is
    :func:`_low_motion`'s rule, that of the ``low_parallax`` verdict too; ``on_bound`` :func:`_on_bound`'s
    reason."""
    if low is not None and result.parallax_px is not None:
        unknown = "the depth is" if pose_known else "the depth and the translation direction are"
        if low.cause is LowMotionCause.PARALLAX:
            warnings.warn(f"cmax.fit: the translation moves the events by under {settings.low_parallax_px:g} px over "
                          f"the window (FitResult.parallax_px): {unknown} poorly constrained; a longer window or a "
                          "faster motion gives more parallax", LowParallaxWarning, stacklevel=3)
        else:
            warnings.warn(f"cmax.fit: {low.reason} (FitResult.quality)", LowParallaxWarning, stacklevel=3)
    kept = [log.stage for log in result.stages if not log.success and not log.at_bound]
    if result.motion_px is not None and (low is not None or kept):
        reason = f"no stage improved on the start ({', '.join(kept)})" if kept else low.reason
        advice = ("" if not kept and low.cause is LowMotionCause.NO_MOTION else
                  f": {CELL_NOISE_ADVICE}" if not kept and low.cause is LowMotionCause.CELL_NOISE else
                  ": the motion is too small to measure reliably; a longer window gives more motion")
        warnings.warn(f"cmax.fit: {reason}{advice}", LowMotionWarning, stacklevel=3)
    bounds = [(log.stage, name) for log in result.stages for name in log.at_bound if not name.startswith("depth_")]
    if bounds:
        raise_bound = "raise " + " / ".join(
            setting for prefix, setting in (("omega_", "FitSettings.max_omega"), ("flow_", "FitSettings.max_flow_px"))
            if any(name.startswith(prefix) for _, name in bounds))
        why = (f"the true value is probably beyond it ({raise_bound})" if low is None else
               f"the window's events do not hold it there ({low.reason}): it is not measured; a longer window gives "
               "more motion" if low.cause in (LowMotionCause.NO_MOTION, LowMotionCause.CELL_NOISE) else
               f"the true value may lie beyond it ({raise_bound}), or the window's events do not hold it there "
               f"({low.reason}: a longer window gives more motion)")
        warnings.warn(f"cmax.fit: {', '.join(f'{n} ({s})' for s, n in bounds)} ended on its bound: {why}; success "
                      "is False", BoundWarning, stacklevel=3)
    if on_bound:
        warnings.warn(f"cmax.fit: {on_bound}; the verdict is ambiguous, not ok", BoundWarning, stacklevel=3)
    depth = [name for log in result.stages for name in log.at_bound if name.startswith("depth_")]
    if depth:
        lo, hi = settings.depth_range
        ends = " and ".join(f"the {'near' if n == 'depth_near' else 'far'} end ({lo if n == 'depth_near' else hi:g} m)"
                            for n in depth)
        why = ("the scene probably lies beyond it, or the speed / pose is in other units (m/s, m); widen depth_range "
               "or check the units" + ("" if low is None else f", or the window's events do not hold the depth there "
                                                              f"({low.reason}: a longer window gives more parallax)"))
        warnings.warn(f"cmax.fit: at least {settings.depth_bound_fraction:.0%} of the events' depth ended on {ends} "
                      f"of depth_range: {why}; success is False", BoundWarning, stacklevel=3)


def event_pixels(x: np.ndarray, y: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixels (H, W) bool that hold at least one of the points ``x, y`` (N,) [px] (rounded to the nearest
    pixel; points outside the image are left out).

    With the events warped to ``t_ref`` by the fitted motion and depth these are
    the event pixels *of the reference view*: where the window's edges are at
    ``t_ref``, the support of ``iwe_after``. The pixels the events were
    recorded at instead form the band each edge swept over the window, and at
    ``t_ref`` half of a moving depth edge's band shows the surface behind it
    (``docs/fitting.md`` compares the two).
    """
    col, row = np.rint(x), np.rint(y)
    inside = (col >= 0) & (col <= width - 1) & (row >= 0) & (row <= height - 1)
    hits = np.zeros((height, width), bool)
    hits[row[inside].astype(np.intp), col[inside].astype(np.intp)] = True
    return hits


def _events_rho(w: Window, grid) -> torch.Tensor:
    """The inverse depth (N,) [1/m] of each of the window's events, interpolated from ``grid`` (gh, gw) [1/m] at its
    node ``w.index, w.weight`` (:meth:`DepthGrid.sample`), in the events' dtype. The window keeps the last grid's
    (read only): a finished fit warps its events by one grid five times (its objective, its reference image, its
    parallax and the permutation test's two warps)."""
    key = np.asarray(grid, np.float64).tobytes()
    kept = getattr(w, "_rho_kept", None)
    if kept is None or kept[0] != key:
        kept = (key, DepthGrid.sample(torch.as_tensor(grid, dtype=w.ev.x.dtype), w.index, w.weight))
        object.__setattr__(w, "_rho_kept", kept)
    return kept[1]


def _warp_with_grid(ev: WarpEvents, dt: torch.Tensor, v, omega, rho: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """se3 warp of the events ``ev`` by ``dt`` (N,) or (B, N) [s] with twist ``v, omega`` and each event's
    inverse depth ``rho`` (N,) [1/m] (interpolated from the depth grid: :func:`_events_rho`)."""
    dtype = ev.x.dtype
    v, omega = torch.as_tensor(v, dtype=dtype), torch.as_tensor(omega, dtype=dtype)
    rows = dt.reshape(-1, dt.shape[-1])
    if all(compiled_warp_applies(ev.rays, row, v, omega, rho) for row in rows):   # the compiled warp, per row
        warped = [warp_se3_compiled(ev.rays, row, v, omega, rho, ev.K) for row in rows]
        return tuple(torch.stack(part).reshape(dt.shape) for part in zip(*warped))
    return warp_se3(ev.rays, dt, v, omega, rho, ev.K)


def _warped(w: Window, motion: Motion, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The fit's events warped by ``dt`` (B, N) [s] with the fitted model (flow, rotation or se3)."""
    ev = w.ev
    with torch.no_grad():
        if motion.flow is not None:
            return warp_flow(ev.x, ev.y, dt, torch.as_tensor(motion.flow, dtype=ev.x.dtype))
        if motion.inverse_depth is None:
            return warp_rotation(ev.rays, dt, torch.as_tensor(motion.omega, dtype=ev.x.dtype), ev.K)
        return _warp_with_grid(ev, dt, motion.v, motion.omega, _events_rho(w, motion.inverse_depth))


def _all_events_at_reference(events: Events, K: np.ndarray, w: Window, v, omega, grid) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres of *all* the window's events (not the fit's subsample, not dithered) warped to ``t_ref``
    by the fitted se3 motion and depth grid: x, y (N,) [px]."""
    ev = WarpEvents.from_events(events, K, dither=False, dtype=torch.float64)
    index, weight = w.grid.weights(ev.x, ev.y)
    with torch.no_grad():
        rho = DepthGrid.sample(torch.as_tensor(grid, dtype=ev.x.dtype), index, weight)
        x, y = _warp_with_grid(ev, ev.dt((0.5,))[0], v, omega, rho)
    return x.numpy(), y.numpy()


def _result(w: Window, events: Events, K: np.ndarray, model: str, motion: Motion, logs: tuple[StageLog, ...], *,
            scale_known: bool, seconds: float, isolated: np.ndarray | None = None,
            warped: tuple[torch.Tensor, torch.Tensor] | None = None) -> FitResult:
    """The :class:`FitResult` of the fitted ``motion`` of window ``w`` (made from ``events`` with intrinsics ``K``
    (3, 3)) after the stages whose ``logs`` are given, in ``seconds``; ``isolated`` (N,) bool: the isolation test of
    ``events`` when at hand; ``warped``: the events warped by ``motion`` to the reference times of ``w.dt``,
    ``x, y`` (B, N) [px], when the caller has them (:func:`_warped`; None: warped here)."""
    ev, s = w.ev, w.settings
    H, W = ev.height, ev.width
    flow, grid = motion.flow, motion.inverse_depth
    v, omega = np.asarray(motion.v, float), np.asarray(motion.omega, float)
    if model != "se3":
        v = np.zeros(3)
    with torch.no_grad():
        before = blur(accumulate_bilinear(ev.x, ev.y, None, H, W), s.sigma).numpy()
        x, y = _warped(w, motion, w.dt_mid)
        after = blur(accumulate_bilinear(x[0], y[0], None, H, W), s.sigma).numpy()
        x_obj, y_obj = _warped(w, motion, w.dt) if warped is None else warped
        objective = float(w.contrast(x_obj, y_obj, 1))
    depth = mask = None
    if grid is not None:
        depth = (1.0 / w.grid.upsample(grid)).astype(np.float32)
        counts = np.bincount(w.cell.numpy(), minlength=grid.size)
        supported = counts.reshape(grid.shape) >= s.min_cell_events
        cell_map = w.grid.cell_of(*[torch.from_numpy(a.ravel().astype(np.float64)) for a in np.mgrid[0:H, 0:W][::-1]])
        x_ref, y_ref = _all_events_at_reference(events, K, w, v, omega, grid)
        if s.mask_isolated_us:                       # background-activity noise: no pixel of its own in the mask
            kept = ~(isolated_events(events.x, events.y, events.t, W, H, s.mask_isolated_us)
                     if isolated is None else isolated)
            x_ref, y_ref = x_ref[kept], y_ref[kept]
        mask = event_pixels(x_ref, y_ref, H, W) & supported.ravel()[cell_map.numpy()].reshape(H, W)
    failed = [log for log in logs if not log.success]
    last = logs[-1].message if logs else ""
    message = "; ".join(f"{log.stage}: {log.message}" for log in failed) if failed else last
    return FitResult(
        model=model, t0_us=ev.t0_us, t1_us=ev.t1_us, t_ref_us=ev.t0_us + (ev.t1_us - ev.t0_us) // 2,
        flow=None if flow is None else np.asarray(flow, float), v=v, omega=omega,
        T=se3_exp(np.r_[v, omega] * ev.duration_s), depth=depth, mask=mask,
        inverse_depth_grid=None if grid is None else np.asarray(grid, float), scale_known=scale_known,
        depth_spread=None if grid is None else depth_spread(np.asarray(grid, float), w.grid),
        objective_before=1.0, objective_after=objective,
        iterations=sum(log.iterations for log in logs), evaluations=sum(log.evaluations for log in logs),
        seconds=seconds, message=message, success=not failed, iwe_before=before, iwe_after=after,
        events_used=len(ev), parallax_px=None if grid is None else _parallax_px(w, v, np.asarray(grid, float)),
        stages=logs, motion_px=None if grid is not None else _motion_px(w, motion),
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


def _motion_px(w: Window, motion: Motion) -> float:
    """Median displacement [px] of the events by the fitted flow or rotation over the whole window."""
    ev = w.ev
    with torch.no_grad():
        x, y = _warped(w, motion, torch.full_like(ev.x, ev.duration_s)[None])
        return float(torch.hypot(x[0] - ev.x, y[0] - ev.y).median())


def _parallax_px(w: Window, v: np.ndarray, grid: np.ndarray) -> float:
    """Median displacement [px] of the events by the translation ``v T`` alone, at their fitted inverse depth."""
    ev = w.ev
    with torch.no_grad():
        x, y = _warp_with_grid(ev, torch.full_like(ev.x, ev.duration_s), v, np.zeros(3), _events_rho(w, grid))
        return float(torch.hypot(x - ev.x, y - ev.y).median())
