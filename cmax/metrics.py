"""Depth and motion metrics against ground truth.

Depth (Eigen et al., NeurIPS 2014; the KITTI / MVSEC conventions):

* ``abs_rel = mean(|d - g| / g)``, ``sq_rel = mean((d - g)^2 / g)``,
  ``rmse = sqrt(mean((d - g)^2))`` [m], ``rmse_log = sqrt(mean((log d - log g)^2))``;
* ``delta_k = mean(max(d / g, g / d) < 1.25^k)``, k = 1, 2, 3;
* ``abs_mean = mean(|d - g|)`` [m], the "Abs mean" of EvtSlowTV's Table 2;
* ``cutoff_errors[c] = mean(|d - g|)`` over the pixels with ``g <= c`` [m], the
  error at 10 / 20 / 30 m cut-offs of EvtSlowTV's Table 3 and of MVSEC's
  depth evaluation (Zhu et al., RA-L 2018).

Motion: RMS errors of the angular velocity [deg/s] and the linear velocity
[m/s], and the angle between the predicted and true translation directions.

Functions are pure: inputs are never modified.

>>> import numpy as np
>>> gt = np.array([[1.0, 2.0], [4.0, np.nan]])
>>> pred = np.array([[1.5, 2.0], [np.nan, 3.0]])
>>> m = depth_metrics(pred, gt)
>>> (m.n_pixels, round(m.coverage, 4), m.abs_mean)
(2, 0.6667, 0.25)
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = ["DepthMetrics", "MotionMetrics", "depth_metrics", "motion_metrics", "window_twist"]

#: Threshold base of the delta accuracies: ``max(d/g, g/d) < 1.25^k``.
DELTA_BASE = 1.25

#: An integer depth map whose largest value exceeds this many metres is warned about: no event data set's depth
#: reaches a kilometre, while integer maps of millimetres or of depth x 256 (KITTI's PNGs) do.
INTEGER_DEPTH_WARN_M = 1000


@dataclass(frozen=True)
class DepthMetrics:
    """Errors of a predicted depth map against ground truth.

    Attributes
    ----------
    abs_rel, sq_rel : float
        ``mean(|d-g|/g)`` [1] and ``mean((d-g)^2/g)`` [m].
    rmse : float
        ``sqrt(mean((d-g)^2))`` [m].
    rmse_log : float
        ``sqrt(mean((log d - log g)^2))`` [1] (natural log), the paper's rms_log.
    delta1, delta2, delta3 : float
        Fractions of pixels with ``max(d/g, g/d) < 1.25^k``.
    abs_mean : float
        ``mean(|d-g|)`` [m], the paper's "Abs mean".
    cutoff_errors : dict[float, float]
        Cut-off [m] -> ``mean(|d-g|)`` over pixels with ``g <= cutoff`` [m];
        NaN where no evaluated pixel lies within the cut-off.
    n_pixels : int
        Number of evaluated pixels (valid ground truth and a prediction), all frames.
    coverage : float
        Evaluated pixels / pixels with valid ground truth (inside ``mask``), all frames.
    scale : float
        Factor applied to the prediction: 1.0 without median scaling; with it,
        the factor of the one frame, or the median of the per-frame factors.
    frame_scales : tuple of float
        Per-frame median-scaling factors (empty without median scaling; NaN for
        a frame with no evaluated pixel).
    n_frames : int
        Frames that have at least one evaluated pixel (with ``per_frame=True``
        the averages run over these).
    """

    abs_rel: float
    sq_rel: float
    rmse: float
    rmse_log: float
    delta1: float
    delta2: float
    delta3: float
    abs_mean: float
    cutoff_errors: dict[float, float]
    n_pixels: int
    coverage: float
    scale: float = 1.0
    frame_scales: tuple[float, ...] = field(default_factory=tuple)
    n_frames: int = 1

    def as_dict(self) -> dict[str, Any]:
        """Flat dict: the cut-off errors become ``err_<cutoff>m`` keys (e.g. ``err_10m``)."""
        out = asdict(self)
        cutoffs = out.pop("cutoff_errors")
        out["frame_scales"] = list(self.frame_scales)
        for cutoff, error in cutoffs.items():
            out[f"err_{cutoff:g}m"] = error
        return out


@dataclass(frozen=True)
class MotionMetrics:
    """Errors of predicted twists against ground truth over N windows.

    Attributes
    ----------
    omega_rms_deg_s : float
        ``sqrt(mean((omega_pred - omega_gt)^2))`` over all windows and the three
        axes [deg/s].
    v_rms_m_s : float
        The same for the linear velocity [m/s].
    direction_error_deg : float
        Mean over windows of the angle between ``v_pred`` and ``v_gt`` [deg];
        windows where either is the zero vector have no direction and are left
        out; NaN when no window has one.
    direction_error_deg_median : float
        Median of the same angles [deg] (NaN likewise).
    n_windows : int
    n_direction : int
        Windows whose direction angle is defined.
    """

    omega_rms_deg_s: float
    v_rms_m_s: float
    direction_error_deg: float
    direction_error_deg_median: float
    n_windows: int
    n_direction: int

    def as_dict(self) -> dict[str, Any]:
        """The fields as a plain dict."""
        return asdict(self)


# -- input checks ---------------------------------------------------------------------------
def _as_depth_stack(array: Any, name: str) -> np.ndarray:
    """``array`` as float64 (N, H, W); raises on other shapes or non-real dtypes."""
    try:
        values = np.asarray(array)
    except Exception as error:  # torch tensors with grad, ragged lists, ...
        raise TypeError(f"{name} must be an array of depths, got {type(array).__name__}: {error}") from None
    if values.dtype == bool or not (np.issubdtype(values.dtype, np.floating)
                                    or np.issubdtype(values.dtype, np.integer)):
        raise TypeError(f"{name} must hold real numbers (depth in metres), got dtype {values.dtype}")
    if values.ndim not in (2, 3) or values.size == 0:
        raise ValueError(f"{name} must have shape (H, W) or (N, H, W) with no empty axis, got {values.shape}")
    if np.issubdtype(values.dtype, np.integer) and values.max() > INTEGER_DEPTH_WARN_M:
        warnings.warn(f"depth_metrics: {name} holds integers ({values.dtype}) up to {values.max():,}, read as metres: "
                      "a depth map of millimetres or of depth x 256 (a KITTI-style PNG)? Convert it to metres first",
                      UserWarning, stacklevel=3)
    values = values.astype(np.float64, copy=False)
    return values[None] if values.ndim == 2 else values


def _as_mask_stack(mask: Any, shape: tuple[int, int, int]) -> np.ndarray:
    """``mask`` as bool of ``shape``; a (H, W) mask applies to every frame."""
    values = np.asarray(mask)
    if values.dtype != bool:
        raise TypeError(f"mask must be a boolean array, got dtype {values.dtype}")
    if values.shape == shape[1:]:
        return np.broadcast_to(values, shape)
    if values.shape != shape:
        raise ValueError(f"mask must have shape {shape[1:]} or {shape}, got {values.shape}")
    return values


def _check_positive(value: float, name: str, *, allow_zero: bool = False) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be a finite {'non-negative' if allow_zero else 'positive'} number, "
                         f"got {value}")
    return float(value)


# -- depth ----------------------------------------------------------------------------------
def _errors(pred: np.ndarray, gt: np.ndarray, cutoffs: tuple[float, ...]) -> dict[str, Any]:
    """Metrics of matching 1-D arrays of positive depths (at least one element)."""
    diff = pred - gt
    abs_diff = np.abs(diff)
    ratio = np.maximum(pred / gt, gt / pred)
    out = {
        "abs_rel": float(np.mean(abs_diff / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(pred) - np.log(gt)) ** 2))),
        "delta1": float(np.mean(ratio < DELTA_BASE)),
        "delta2": float(np.mean(ratio < DELTA_BASE**2)),
        "delta3": float(np.mean(ratio < DELTA_BASE**3)),
        "abs_mean": float(np.mean(abs_diff)),
    }
    for cutoff in cutoffs:
        within = gt <= cutoff
        out[f"cut{cutoff}"] = float(np.mean(abs_diff[within])) if within.any() else float("nan")
    return out


def depth_metrics(
    pred: Any, gt: Any, *, mask: Any = None, median_scaling: bool = False,
    cutoffs: tuple[float, ...] = (10.0, 20.0, 30.0), per_frame: bool = False,
    min_depth: float = 1e-3, max_depth: float | None = None,
) -> DepthMetrics:
    """Depth errors of ``pred`` against ``gt`` on the pixels where both are valid.

    Parameters
    ----------
    pred : array_like, shape (H, W) or (N, H, W)
        Predicted z-depth [m]. NaN (also +-inf and values <= 0) means "not
        predicted": such pixels are not evaluated and lower ``coverage``; negative
        depths where the ground truth is valid are warned about (a sign error is
        not an absent prediction). Predictions are not clipped to
        ``[min_depth, max_depth]`` (monodepth2's evaluation clips them to
        [1e-3, 80] m: clip them first to compare with its figures).
    gt : array_like, same shape as ``pred``
        Ground-truth z-depth [m]. Valid where finite and ``> min_depth`` (and
        ``<= max_depth`` if given); other pixels (NaN sky, holes) are ignored.
        An integer map (of either) beyond :data:`INTEGER_DEPTH_WARN_M` is warned
        about (millimetres, or KITTI's depth x 256, read as metres).
    mask : array_like of bool, shape (H, W) or like ``gt``, optional
        Pixels to evaluate (e.g. the event mask); a (H, W) mask applies to every frame.
    median_scaling : bool
        Multiply each frame's prediction by ``median(g) / median(d)`` over its
        evaluated pixels (for predictions known only up to scale); the factor is
        reported in ``scale`` / ``frame_scales``.
    cutoffs : tuple of float
        Depth cut-offs [m] of ``cutoff_errors``.
    per_frame : bool
        True: compute each metric per frame, then average over the frames that
        have evaluated pixels (cut-off errors: over the frames with pixels within
        the cut-off). False: pool all pixels of all frames.
    min_depth, max_depth : float
        Range of valid ground truth [m].

    Returns
    -------
    DepthMetrics

    Raises
    ------
    ValueError
        Shapes differ, bad options, or no pixel has both valid ground truth and
        a prediction (the metrics would be undefined).
    TypeError
        Non-numeric inputs or a non-boolean mask.
    """
    pred_stack = _as_depth_stack(pred, "pred")
    gt_stack = _as_depth_stack(gt, "gt")
    if pred_stack.shape != gt_stack.shape:
        raise ValueError(f"pred and gt must have the same shape, got {np.shape(pred)} and {np.shape(gt)}")
    min_depth = _check_positive(min_depth, "min_depth", allow_zero=True)
    if max_depth is not None and _check_positive(max_depth, "max_depth") <= min_depth:
        raise ValueError(f"max_depth must exceed min_depth={min_depth}, got {max_depth}")
    cutoffs = tuple(_check_positive(c, "cutoffs[]") for c in cutoffs)

    with np.errstate(invalid="ignore"):
        valid_gt = np.isfinite(gt_stack) & (gt_stack > min_depth)
        if max_depth is not None:
            valid_gt &= gt_stack <= max_depth
        if mask is not None:
            valid_gt &= _as_mask_stack(mask, gt_stack.shape)
        evaluated = valid_gt & np.isfinite(pred_stack) & (pred_stack > 0)
        negative = valid_gt & (pred_stack < 0) & np.isfinite(pred_stack)
    n_valid_gt = int(valid_gt.sum())
    n_pixels = int(evaluated.sum())
    if n_pixels == 0:
        with np.errstate(invalid="ignore"):
            positive = int((np.isfinite(pred_stack) & (pred_stack > 0)).sum())
        raise ValueError(
            f"no pixel has both valid ground truth and a prediction ({n_valid_gt} pixels of valid ground truth"
            f"{' inside mask' if mask is not None else ''}, {positive} positive finite predictions"
            f"{f', {int(negative.sum())} negative ones' if negative.any() else ''})"
        )
    if negative.any():
        warnings.warn(f"depth_metrics: pred holds {int(negative.sum()):,} negative depths (down to "
                      f"{float(pred_stack[negative].min()):.3g} m) where the ground truth is valid: they count as not "
                      f"predicted (coverage {n_pixels / n_valid_gt:.3f}), not as errors; a sign error, or an inverse "
                      "depth or disparity of the wrong sign?", UserWarning, stacklevel=2)

    frames = [(pred_stack[i][evaluated[i]], gt_stack[i][evaluated[i]]) for i in range(len(gt_stack))]
    frame_scales: tuple[float, ...] = ()
    if median_scaling:
        frame_scales = tuple(float(np.median(g) / np.median(d)) if d.size else float("nan") for d, g in frames)
        frames = [(d * s, g) for (d, g), s in zip(frames, frame_scales)]
        scale = float(np.nanmedian(frame_scales))
    else:
        scale = 1.0
    frames = [(d, g) for d, g in frames if d.size]

    if per_frame:
        per = [_errors(d, g, cutoffs) for d, g in frames]
        values = {key: _mean_of_finite([p[key] for p in per]) for key in per[0]}
    else:
        values = _errors(np.concatenate([d for d, _ in frames]), np.concatenate([g for _, g in frames]), cutoffs)
    cutoff_errors = {c: values.pop(f"cut{c}") for c in cutoffs}
    return DepthMetrics(
        **values, cutoff_errors=cutoff_errors, n_pixels=n_pixels, coverage=n_pixels / n_valid_gt,
        scale=scale, frame_scales=frame_scales, n_frames=len(frames),
    )


def _mean_of_finite(values: list[float]) -> float:
    """Mean of the finite values; NaN when there is none (a cut-off no frame reaches)."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


# -- motion ---------------------------------------------------------------------------------
def _as_vectors(array: Any, name: str) -> np.ndarray:
    try:
        values = np.asarray(array, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise TypeError(f"{name} must be an array of numbers, got {type(array).__name__}: {error}") from None
    if values.ndim not in (1, 2) or values.shape[-1] != 3 or values.size == 0:
        raise ValueError(f"{name} must have shape (3,) or (N, 3), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{name} must be finite, got {int((~np.isfinite(values)).sum())} non-finite entries")
    return values.reshape(-1, 3)


def direction_angles_deg(v_pred: np.ndarray, v_gt: np.ndarray) -> np.ndarray:
    """Angle between the rows of ``v_pred`` and ``v_gt`` (N, 3) [deg]; NaN where either row is zero.

    Uses ``atan2(|a x b|, a . b)``, accurate also for nearly parallel vectors.
    """
    cross = np.linalg.norm(np.cross(v_pred, v_gt), axis=1)
    dot = np.einsum("ij,ij->i", v_pred, v_gt)
    angles = np.degrees(np.arctan2(cross, dot))
    zero = (np.linalg.norm(v_pred, axis=1) == 0) | (np.linalg.norm(v_gt, axis=1) == 0)
    return np.where(zero, np.nan, angles)


def motion_metrics(v_pred: Any, omega_pred: Any, v_gt: Any, omega_gt: Any) -> MotionMetrics:
    """Errors of predicted camera twists against ground truth.

    Parameters
    ----------
    v_pred, v_gt : array_like, shape (3,) or (N, 3)
        Linear velocity in the camera frame [m/s] (for predictions known only
        up to scale, only ``direction_error_deg`` is meaningful).
    omega_pred, omega_gt : array_like, shape like ``v_pred``
        Angular velocity in the camera frame [rad/s].

    Returns
    -------
    MotionMetrics
        RMS errors over all windows and axes; the direction angle is undefined
        (left out, NaN if none is left) for windows where ``|v_gt|`` or
        ``|v_pred|`` is zero.

    Raises
    ------
    ValueError
        Shapes other than (3,) / (N, 3), shapes that differ, non-finite values.

    Examples
    --------
    >>> import numpy as np
    >>> m = motion_metrics([1, 0, 0], [0, 0, 0], [0, 1, 0], [0, 0, np.radians(2)])
    >>> round(m.direction_error_deg, 6), round(m.omega_rms_deg_s ** 2 * 3, 6)
    (90.0, 4.0)
    """
    arrays = {name: _as_vectors(a, name) for name, a in
              (("v_pred", v_pred), ("omega_pred", omega_pred), ("v_gt", v_gt), ("omega_gt", omega_gt))}
    shapes = {name: np.shape(a) for name, a in
              (("v_pred", v_pred), ("omega_pred", omega_pred), ("v_gt", v_gt), ("omega_gt", omega_gt))}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"v_pred, omega_pred, v_gt and omega_gt must have the same shape, got {shapes}")
    omega_error_deg = np.degrees(arrays["omega_pred"] - arrays["omega_gt"])
    v_error = arrays["v_pred"] - arrays["v_gt"]
    angles = direction_angles_deg(arrays["v_pred"], arrays["v_gt"])
    defined = angles[np.isfinite(angles)]
    return MotionMetrics(
        omega_rms_deg_s=float(np.sqrt(np.mean(omega_error_deg**2))),
        v_rms_m_s=float(np.sqrt(np.mean(v_error**2))),
        direction_error_deg=float(np.mean(defined)) if defined.size else float("nan"),
        direction_error_deg_median=float(np.median(defined)) if defined.size else float("nan"),
        n_windows=len(angles), n_direction=int(defined.size),
    )


def window_twist(T_w_0: Any, T_w_1: Any, duration_s: float) -> np.ndarray:
    """Constant body twist ``(v [m/s], omega [rad/s])`` (6,) taking pose ``T_w_0`` to ``T_w_1`` in ``duration_s``.

    ``xi = se3_log(T_w_0^-1 T_w_1) / duration_s``: the mean motion of a window in the
    frame of its first camera, the ground truth of :func:`cmax.fit`'s ``(v, omega)``.

    Parameters
    ----------
    T_w_0, T_w_1 : array_like, shape (4, 4)
        Camera-to-world poses at the window's first and last event.
    duration_s : float
        Time between them [s], positive.
    """
    from cmax.geometry import invert_pose, se3_log

    if isinstance(duration_s, (bool, np.bool_)) or not np.isfinite(duration_s) or not duration_s > 0:
        raise ValueError(f"duration_s must be a positive number of seconds, got {duration_s}")
    return se3_log(invert_pose(T_w_0) @ np.asarray(T_w_1, dtype=np.float64)) / float(duration_s)
