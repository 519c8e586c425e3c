"""Frames between two video frames: linear blending and DIS optical-flow warping.

Used by the adaptive sampling of :mod:`cmax.sim.sampling`; an *interval pair*
renders the frame at any fraction ``alpha`` in [0, 1] of the interval between
two grey frames ``I0`` (alpha 0) and ``I1`` (alpha 1).

* ``"linear"``: ``I(a) = (1 - a) I0 + a I1`` in intensity. Its log intensity
  ``L = log(I/255 + eps)`` is known in closed form, so
  :meth:`LinearPair.max_step` gives the exact largest step after ``a`` that
  keeps every pixel's ``|dL|`` within a bound.
* ``"flow"``: dense optical flow by DIS (Kroeger et al. 2016, OpenCV's
  ``cv2.DISOpticalFlow``), forward ``F01`` and backward ``F10``, computed
  **once per interval**. The flows toward time ``a`` are approximated as in
  Super SloMo (Jiang et al. 2018), ``F_a0 = -(1-a) a F01 + a^2 F10`` and
  ``F_a1 = (1-a)^2 F01 - a (1-a) F10``; both frames are warped toward time
  ``a`` (``cv2.remap``, bilinear, border replicated) and blended with weights
  ``(1 - a, a)``. Flow is *unreliable* at a pixel when it fails the
  forward-backward check (Sundaram et al. 2010:
  ``|F01 + F10(x + F01)|^2 > 0.01 (|F01|^2 + |F10(x + F01)|^2) + 0.5``), points
  outside the frame, or does not explain the change better than no motion
  (photometric error after warping, 5x5 box mean, larger than the error of
  the unwarped frames plus 1 grey level: a pure brightness change). The
  reliability maps are warped along with the frames, and the output is
  ``m * flow_blend + (1 - m) * linear_blend`` with ``m = V0 * V1``, which
  equals ``I0`` at ``a = 0`` and ``I1`` at ``a = 1`` and is continuous in ``a``.
  :attr:`FlowPair.motion_px` is the largest displacement the flow applies.

References
----------
T. Kroeger, R. Timofte, D. Dai, L. Van Gool. "Fast Optical Flow using Dense Inverse
Search." ECCV 2016. https://doi.org/10.1007/978-3-319-46493-0_29
H. Jiang et al. "Super SloMo: High Quality Estimation of Multiple Intermediate Frames
for Video Interpolation." CVPR 2018.
N. Sundaram, T. Brox, K. Keutzer. "Dense Point Trajectories by GPU-Accelerated Large
Displacement Optical Flow." ECCV 2010.
"""
from __future__ import annotations

import math
from typing import Iterable, Literal, Protocol

import cv2
import numpy as np

__all__ = [
    "LOG_EPS",
    "MIN_FLOW_SIZE",
    "FlowPair",
    "LinearPair",
    "Method",
    "check_method",
    "interpolate_frames",
    "log_intensity",
    "make_pair",
]

#: ``eps`` of ``L = log(I/255 + eps)``.
LOG_EPS = 1e-3
#: Smallest frame side (pixels) for ``method="flow"``: OpenCV's DIS flow fails or
#: crashes on smaller or very flat frames.
MIN_FLOW_SIZE = 32

Method = Literal["flow", "linear"]
PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
_FLOOR = np.float32(255 * LOG_EPS)  # grey value where the log intensity's slope flattens


def log_intensity(frame: np.ndarray) -> np.ndarray:
    """Log intensity ``L = log(I/255 + LOG_EPS)`` of a grey frame.

    Parameters
    ----------
    frame : ndarray, shape (..., H, W)
        Grey values in [0, 255] (any real dtype).

    Returns
    -------
    ndarray, float32, same shape.
    """
    return np.log(np.asarray(frame, dtype=np.float32) * np.float32(1 / 255) + np.float32(LOG_EPS))


class Pair(Protocol):
    """Frames of one interval: ``frame(alpha)``, (H, W) float32, alpha in [0, 1]."""

    def frame(self, alpha: float) -> np.ndarray: ...


class LinearPair:
    """``(1 - a) I0 + a I1``, with the exact largest step of :meth:`max_step`."""

    def __init__(self, frame0: np.ndarray, frame1: np.ndarray, bound: float | None = None) -> None:
        self.frame0 = frame0
        self.delta = frame1 - frame0
        self._bound = None
        if bound is not None:
            self._set_bound(bound)

    def _set_bound(self, bound: float) -> None:
        # |log(v + s d) - log(v)| <= B  <=>  s <= v / (|d| k), k = 1/expm1(B) up, 1/-expm1(-B) down
        up, down = 1.0 / math.expm1(bound), 1.0 / -math.expm1(-bound)
        self._weight = np.abs(self.delta) * np.where(self.delta > 0, np.float32(up), np.float32(down))
        self._bound = bound

    def frame(self, alpha: float) -> np.ndarray:
        return self.frame0 + np.float32(alpha) * self.delta

    def max_step(self, frame: np.ndarray, bound: float) -> float:
        """Largest fraction ``s`` of the interval after ``frame`` (this pair's frame at some
        ``a``) such that no pixel's ``L`` changes by more than ``bound`` from ``a`` to ``a + s``.

        Exact for linear blending: ``min over pixels of (I(a) + 255 eps) / (|d| k)``.
        """
        if self._bound != bound:
            self._set_bound(bound)
        rate = float(np.max(self._weight / (frame + _FLOOR)))
        return math.inf if rate == 0 else 1.0 / rate


def _warp(images: tuple[np.ndarray, ...], displacement: np.ndarray,
          grid: np.ndarray) -> list[np.ndarray]:
    """Each (H, W) float32 image sampled at ``x + displacement(x)``, bilinear, border replicated.

    One ``cv2.remap`` per single-channel image: OpenCV 5 interpolates
    one-channel float images at the exact map position, but quantises the map
    to 1/32 pixel for two-channel images, which makes values jump.
    """
    positions = grid + displacement
    return [cv2.remap(image, positions, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            for image in images]


def _reliability(frame0: np.ndarray, frame1: np.ndarray, flow01: np.ndarray,
                 flow10: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Soft map (H, W) float32 in [0, 1]: 1 where ``flow01`` (at frame-0 pixels) is reliable."""
    height, width = frame0.shape
    back = np.dstack(_warp(tuple(np.ascontiguousarray(flow10[..., i]) for i in (0, 1)), flow01, grid))
    err = np.sum((flow01 + back) ** 2, axis=2)
    ok = err <= 0.01 * (np.sum(flow01**2, axis=2) + np.sum(back**2, axis=2)) + 0.5
    target = grid + flow01
    ok &= (target[..., 0] >= 0) & (target[..., 0] <= width - 1)
    ok &= (target[..., 1] >= 0) & (target[..., 1] <= height - 1)
    (warped,) = _warp((frame1,), flow01, grid)
    e_flow = cv2.blur(np.abs(warped - frame0), (5, 5))
    e_still = cv2.blur(np.abs(frame1 - frame0), (5, 5))
    ok &= e_flow <= e_still + 1.0
    return cv2.GaussianBlur(ok.astype(np.float32), (0, 0), 1.0)


class FlowPair:
    """Flow-based interpolation of one interval (see the module docstring)."""

    def __init__(self, frame0: np.ndarray, frame1: np.ndarray, dis: cv2.DISOpticalFlow,
                 grid: np.ndarray) -> None:
        u0 = np.clip(np.rint(frame0), 0, 255).astype(np.uint8)
        u1 = np.clip(np.rint(frame1), 0, 255).astype(np.uint8)
        self.flow01 = dis.calc(u0, u1, None)
        self.flow10 = dis.calc(u1, u0, None)
        self.grid = grid
        self.frame0 = frame0
        self.delta = frame1 - frame0
        self.sources0 = (frame0, _reliability(frame0, frame1, self.flow01, self.flow10, grid))
        self.sources1 = (frame1, _reliability(frame1, frame0, self.flow10, self.flow01, grid))
        self.motion_px = max(_largest_motion(self.flow01, self.sources0[1]),
                             _largest_motion(self.flow10, self.sources1[1]))

    def frame(self, alpha: float) -> np.ndarray:
        a = float(alpha)
        d0 = cv2.addWeighted(self.flow01, -(1 - a) * a, self.flow10, a * a, 0.0)
        d1 = cv2.addWeighted(self.flow01, (1 - a) ** 2, self.flow10, -a * (1 - a), 0.0)
        warped0, valid0 = _warp(self.sources0, d0, self.grid)
        warped1, valid1 = _warp(self.sources1, d1, self.grid)
        a32 = np.float32(a)
        linear = self.frame0 + a32 * self.delta
        flow = warped0 + a32 * (warped1 - warped0)
        return linear + (valid0 * valid1) * (flow - linear)



def _largest_motion(flow: np.ndarray, reliability: np.ndarray) -> float:
    """Largest displacement (pixels) of ``flow`` (H, W, 2) where it is used (reliability > 0)."""
    length = np.hypot(flow[..., 0], flow[..., 1])
    used = reliability > 0
    return float(length[used].max()) if used.any() else 0.0


def check_method(method: object, flow_preset: object) -> None:
    """Raise ValueError for an unknown ``method`` or ``flow_preset``."""
    if method not in ("flow", "linear"):
        raise ValueError(f"method must be 'flow' or 'linear', got {method!r}")
    if flow_preset not in PRESETS:
        raise ValueError(f"flow_preset must be one of {sorted(PRESETS)}, got {flow_preset!r}")


def make_pair(frame0: np.ndarray, frame1: np.ndarray, method: str, flow_preset: str,
              state: dict[str, object]) -> LinearPair | FlowPair:
    """The interval pair of ``method``; ``state`` keeps the DIS instance and pixel grid."""
    if method == "linear":
        return LinearPair(frame0, frame1)
    if "dis" not in state:
        state["dis"] = cv2.DISOpticalFlow_create(PRESETS[flow_preset])
        height, width = frame0.shape
        state["grid"] = np.dstack(np.meshgrid(np.arange(width, dtype=np.float32),
                                              np.arange(height, dtype=np.float32)))
    return FlowPair(frame0, frame1, state["dis"], state["grid"])  # type: ignore[arg-type]


def check_frame(frame: object, index: int, shape: tuple[int, ...] | None,
                method: str) -> np.ndarray:
    """A float32 (H, W) copy of input frame ``index``, with shape and range checks."""
    array = np.asarray(frame)
    if array.dtype.kind not in "uif":
        raise TypeError(f"frame {index} must hold grey values, got dtype {array.dtype}")
    if array.ndim == 3 and array.shape[2] == 3 and array.dtype in (np.uint8, np.float32):
        array = cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_BGR2GRAY)  # BGR, as ESIM
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(f"frame {index} must have shape (H, W) or (H, W, 3) BGR, got {array.shape}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"frame {index} has shape {array.shape}, the first frame {shape}")
    if method == "flow" and min(array.shape) < MIN_FLOW_SIZE:
        raise ValueError(f"method='flow' needs frames of at least {MIN_FLOW_SIZE}x{MIN_FLOW_SIZE} pixels, got "
                         f"{array.shape[1]}x{array.shape[0]} (width x height); use method='linear' "
                         "(cmax simulate: --method linear)")
    out = np.array(array, dtype=np.float32)
    low, high = float(out.min()), float(out.max())
    if not (0 <= low and high <= 255):  # also catches NaN
        raise ValueError(f"frame {index} must hold grey values in [0, 255], got [{low}, {high}]")
    return out


def interpolate_frames(
    frame0: np.ndarray,
    frame1: np.ndarray,
    alphas: Iterable[float],
    *,
    method: Method = "flow",
    flow_preset: Literal["ultrafast", "fast", "medium"] = "medium",
) -> np.ndarray:
    """Frames between ``frame0`` (alpha 0) and ``frame1`` (alpha 1), as the sampler makes them.

    Parameters
    ----------
    frame0, frame1 : array_like, shape (H, W)
        Grey frames in [0, 255].
    alphas : iterable of float, each in [0, 1]
        Fractions of the interval.
    method : {"flow", "linear"}
        DIS optical flow warping (frames at least 32x32) or linear blending.
    flow_preset : {"ultrafast", "fast", "medium"}
        DIS preset for ``method="flow"``.

    Returns
    -------
    ndarray, float32, shape (K, H, W)

    Examples
    --------
    >>> import numpy as np
    >>> a, b = np.zeros((32, 32), np.float32), np.full((32, 32), 100, np.float32)
    >>> interpolate_frames(a, b, [0.25], method="linear")[0, 0, 0]
    np.float32(25.0)
    """
    check_method(method, flow_preset)
    f0 = check_frame(frame0, 0, None, str(method))
    f1 = check_frame(frame1, 1, f0.shape, str(method))
    alphas = np.asarray(list(alphas), dtype=np.float64).reshape(-1)
    if np.any(~np.isfinite(alphas)) or np.any((alphas < 0) | (alphas > 1)):
        raise ValueError("alphas must lie in [0, 1]")
    pair = make_pair(f0, f1, str(method), str(flow_preset), {})
    if alphas.size == 0:
        return np.empty((0,) + f0.shape, np.float32)
    return np.stack([pair.frame(float(a)) for a in alphas])
