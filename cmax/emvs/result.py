"""Results of EMVS: the vote volume (:class:`DSI`) and the semi-dense depth map (:class:`SemiDenseDepth`).

:func:`semi_dense_depth` turns a DSI into a depth map as EMVS does (Rebecq et
al., IJCV 2018, section 4.3): depth = the plane of most votes along each
pixel's ray, confidence = that maximum, a semi-dense mask by adaptive Gaussian
thresholding of the confidence map, and a median filter of the depth.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from cmax._jit import kernel
from cmax.hot_pixels import no_pixels

if TYPE_CHECKING:  # pragma: no cover
    from cmax import viz

__all__ = ["DSI", "SemiDenseDepth", "semi_dense_depth", "plane_argmax", "depth_scale_bar", "write_ply",
           "NoBaselineWarning", "MIN_PARALLAX_PX"]

#: Below this parallax [px] between the nearest and the farthest plane, no depth is given.
MIN_PARALLAX_PX = 1.0


class NoBaselineWarning(UserWarning):
    """The camera barely translated (``DSI.parallax_px`` below :data:`MIN_PARALLAX_PX`): the planes
    cannot be told apart, so EMVS returns no depth (an empty mask) instead of the near plane."""


@dataclass(frozen=True, eq=False)
class DSI:
    """Disparity Space Image: ray votes on planes of the reference view.

    Attributes
    ----------
    votes : ndarray, shape (n_planes, H, W), float32
        Votes per plane (nearest plane first) and reference pixel.
    depths : ndarray, shape (n_planes,), float64
        z-depth of each plane in the reference view [m], uniform in inverse depth.
    K : ndarray, shape (3, 3)
        Pinhole of the reference view (undistorted pixels).
    t_ref_us : int
        Time of the reference view [µs].
    T_w_ref : ndarray, shape (4, 4)
        Pose of the reference view (camera-to-world).
    n_events : int
        Events that voted (rays that meet the planes in front of their camera).
    seconds : float
        Wall time of the voting [s].
    parallax_px : float
        Largest displacement [px] of a ray's votes between the nearest and the farthest
        plane over the camera positions of the events: ``(1/near - 1/far)`` times the
        largest ``f |t_xy| + r |t_z|`` of a camera centre ``t`` in the reference frame
        (``f`` the focal length, ``r`` the largest distance of the principal point to
        the border). NaN when unknown (a DSI built by hand).
    hot_pixels : ndarray, shape (K, 2), int64
        ``(x, y)`` of the hot pixels whose events did not vote (``EMVS.hot_pixels``); empty when none.
    """

    votes: np.ndarray
    depths: np.ndarray
    K: np.ndarray
    t_ref_us: int
    T_w_ref: np.ndarray
    n_events: int
    seconds: float
    parallax_px: float = float("nan")
    hot_pixels: np.ndarray = field(default_factory=no_pixels)


@dataclass(frozen=True, eq=False)
class SemiDenseDepth:
    """Semi-dense depth map of EMVS in the reference view, and its point cloud.

    Attributes
    ----------
    depth : ndarray, shape (H, W), float32
        z-depth [m] in the reference view; NaN outside ``mask``.
    confidence : ndarray, shape (H, W), float32
        Maximum of the DSI along each pixel's ray (votes).
    mask : ndarray, shape (H, W), bool
        Semi-dense mask (adaptive Gaussian threshold of the confidence).
    points : ndarray, shape (P, 3), float64
        The masked pixels back-projected with their depth, in the world frame [m]
        (row-major order of the mask).
    t_ref_us : int
        Time of the reference view [µs].
    T_w_ref : ndarray, shape (4, 4)
        Pose of the reference view (camera-to-world).
    depth_range : tuple of float
        ``(near, far)`` of the planes [m].
    n_planes : int
    seconds : float
        Wall time of the whole run [s].
    K : ndarray, shape (3, 3)
        Pinhole of the reference view.
    n_events : int
        Events that voted.
    hot_pixels : ndarray, shape (K, 2), int64
        ``(x, y)`` of the hot pixels whose events did not vote (``EMVS.hot_pixels``); empty when none.
    """

    depth: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    points: np.ndarray
    t_ref_us: int
    T_w_ref: np.ndarray
    depth_range: tuple[float, float]
    n_planes: int
    seconds: float
    K: np.ndarray
    n_events: int
    hot_pixels: np.ndarray = field(default_factory=no_pixels)

    def image(self, scale: "viz.DepthScale | tuple[float, float] | None" = None, *,
              zoom: int | None = None, metric: bool = True) -> np.ndarray:
        """Picture (BGR uint8): the confidence map (the DSI's maximum per pixel; its grey scale in the title:
        white no vote, black the 99th percentile of the votes and above) beside the depth with its colour bar [m];
        ``metric=False`` (poses up to scale, e.g. a trajectory of ``cmax fit`` without ``--speed``): the depth
        titled ``up to scale`` and its colour bar without a unit.

        ``scale`` (a :class:`cmax.viz.DepthScale`, or ``(near, far)`` metres) gives several maps one
        colour scale; default: the 1st-99th percentiles of the map's own depths (the DSI's depth range when
        the mask is empty), so that a scene in a wide range (a 0.5-200 m hike, most of it beyond 5 m) is not
        drawn in the darkest few colours. No estimate is drawn as a grey hatch.
        ``zoom``: each pixel of the maps drawn as a ``zoom x zoom`` block (default
        :func:`cmax.viz.readable_zoom`: a small sensor's picture enlarged until its labels are readable).
        """
        from cmax import viz

        zoom = viz.readable_zoom(self.depth.shape[1]) if zoom is None else zoom

        confidence = self.confidence
        top = float(np.percentile(confidence[confidence > 0], 99)) if np.any(confidence > 0) else 1.0
        grey = viz.enlarge((255 * (1.0 - np.clip(confidence / top, 0, 1))).astype(np.uint8), zoom)
        depth = viz.enlarge(np.where(self.mask, self.depth, np.nan), zoom)
        return viz.hstack([
            viz.titled(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR), confidence_title(top)),
            viz.depth_panel(depth, self._own_scale() if scale is None else scale,
                            f"semi-dense depth{'' if metric else ' [up to scale]'}, {int(self.mask.sum())} px",
                            unit="m" if metric else ""),
        ])

    def on_bounds(self) -> dict[str, float]:
        """Shares of the masked pixels whose depth lies on the nearest or the farthest plane (within half a plane
        step, the planes being uniform in inverse depth): ``{"near": ..., "far": ...}``. A pile-up on the far
        plane is the scene beyond the range, or rays with too little parallax to tell (both ends are clips, not
        measurements)."""
        near, far = self.depth_range
        depths = self.depth[self.mask].astype(np.float64)
        if not depths.size:
            return {"near": 0.0, "far": 0.0}
        half_step = 0.5 * (1.0 / near - 1.0 / far) / max(self.n_planes - 1, 1)
        inverse = 1.0 / depths
        return {"near": float(np.mean(inverse >= 1.0 / near - half_step)),
                "far": float(np.mean(inverse <= 1.0 / far + half_step))}

    def _own_scale(self) -> "viz.DepthScale":
        """The colour scale of :meth:`image` by default: the map's own depths, or the DSI's range."""
        from cmax import viz

        if not np.any(self.mask):
            return viz.DepthScale(*self.depth_range)
        return viz.DepthScale.from_depths(self.depth[self.mask])

    def plot(self, path: str | os.PathLike, *, zoom: int | None = None, metric: bool = True) -> Path:
        """Write :meth:`image` (``zoom``, ``metric`` as there) as a PNG (atomically); returns the path."""
        from cmax import viz

        return viz.save_png(path, self.image(zoom=zoom, metric=metric))

    def save_ply(self, path: str | os.PathLike, *, binary: bool = True) -> Path:
        """Write :attr:`points` (world frame, metres) as a PLY point cloud at ``path`` (atomically; ``binary``:
        little-endian float32, else ASCII); returns the path."""
        return write_ply(path, self.points, binary=binary)


@kernel
def _median_kernel(depth, mask, radius, out):
    """``out[r, c]`` = median of ``depth`` over the masked pixels of the window around each masked ``(r, c)``.

    float32 arithmetic as ``np.nanmedian``: the middle value, or the float32 sum of the two middle
    values halved.
    """
    height, width = depth.shape
    values = np.empty((2 * radius + 1) ** 2, depth.dtype)
    for r in range(height):
        for c in range(width):
            if not mask[r, c]:
                continue
            n = 0
            for y in range(max(0, r - radius), min(height, r + radius + 1)):
                for x in range(max(0, c - radius), min(width, c + radius + 1)):
                    if mask[y, x]:
                        value = depth[y, x]
                        j = n  # insertion sort of the few window values
                        while j > 0 and values[j - 1] > value:
                            values[j] = values[j - 1]
                            j -= 1
                        values[j] = value
                        n += 1
            middle = n // 2
            out[r, c] = values[middle] if n % 2 else (values[middle - 1] + values[middle]) / 2


def _masked_median(depth: np.ndarray, mask: np.ndarray, size: int) -> np.ndarray:
    """Median of the masked depths in the ``size`` x ``size`` window of every masked pixel (H, W) float32.

    NaN outside the mask; the masked depths must be finite. One compiled pass.
    """
    out = np.full(depth.shape, np.nan, np.float32)
    if mask.any():
        _median_kernel(np.ascontiguousarray(depth, dtype=np.float32), np.ascontiguousarray(mask, dtype=bool),
                       size // 2, out)
    return out


@kernel
def _argmax_planes(votes, index, best):
    """First plane of the largest vote per cell of ``votes`` (P, n): ``index`` (n,) int64, ``best`` (n,)."""
    index[:] = 0
    best[:] = votes[0]
    for k in range(1, votes.shape[0]):
        plane = votes[k]
        for i in range(votes.shape[1]):
            value = plane[i]
            # np.argmax: the first maximum, and the first NaN when there is one.
            if value > best[i] or (value != value and best[i] == best[i]):
                best[i] = value
                index[i] = k


def plane_argmax(votes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.argmax(votes, axis=0)`` and the maximum itself, in one pass over the planes.

    Parameters
    ----------
    votes : ndarray, shape (n_planes, H, W), float32 or float64
        Must have at least one plane.

    Returns
    -------
    index : ndarray, shape (H, W), int64
        First plane of the largest vote (of the first NaN, as ``np.argmax``).
    maximum : ndarray, shape (H, W), float32
        ``votes[index]`` cast to float32.
    """
    if votes.ndim != 3 or votes.shape[0] < 1:
        raise ValueError(f"votes must have shape (n_planes, H, W) with n_planes >= 1, got {votes.shape}")
    if votes.dtype not in (np.float32, np.float64):
        index = np.argmax(votes, axis=0)
        return index, np.take_along_axis(votes, index[None], axis=0)[0].astype(np.float32)
    flat = np.ascontiguousarray(votes).reshape(votes.shape[0], -1)
    index = np.empty(flat.shape[1], np.int64)
    best = np.empty(flat.shape[1], votes.dtype)
    _argmax_planes(flat, index, best)
    return index.reshape(votes.shape[1:]), best.astype(np.float32).reshape(votes.shape[1:])


def semi_dense_depth(dsi: DSI, *, threshold_kernel: int = 5, threshold_c: float = 5.0,
                     median_size: int = 5, seconds: float | None = None) -> SemiDenseDepth:
    """Depth map of a DSI: argmax along depth, confidence, adaptive Gaussian mask, median filter.

    Parameters
    ----------
    dsi : DSI
    threshold_kernel : int
        Odd window of ``cv2.adaptiveThreshold`` (Gaussian weights) [px].
    threshold_c : float
        A pixel is kept when its confidence, scaled to 0-255 by the map's
        maximum, exceeds the Gaussian-weighted local mean by more than this.
    median_size : int
        Odd window of the median filter of the depth [px]; the median is taken
        over the masked pixels of the window (1 disables it).
    seconds : float, optional
        Wall time to record (default: the DSI's).

    Returns
    -------
    SemiDenseDepth
        With an empty mask (depth all NaN, no points) and a :class:`NoBaselineWarning`
        when ``dsi.parallax_px`` is below :data:`MIN_PARALLAX_PX`: without camera
        translation every plane gets the same votes, and the argmax would be the
        near plane, a confident wrong answer.
    """
    index, confidence = plane_argmax(dsi.votes)
    peak = float(confidence.max())
    no_baseline = bool(dsi.parallax_px < MIN_PARALLAX_PX)  # False for NaN (unknown)
    if no_baseline:
        warnings.warn(
            f"EMVS: the camera translation moves a ray's votes by only {dsi.parallax_px:.3g} px between the "
            f"nearest and the farthest plane (under {MIN_PARALLAX_PX} px): depth cannot be resolved without "
            "camera motion; no depth is returned (empty mask)", NoBaselineWarning, stacklevel=3,
        )
        mask = np.zeros(confidence.shape, bool)
    elif peak > 0:
        scaled = np.round(255.0 * confidence / peak).astype(np.uint8)
        mask = cv2.adaptiveThreshold(scaled, 1, cv2.ADAPTIVE_THRESH_GAUSSIAN_C, cv2.THRESH_BINARY,
                                     threshold_kernel, -threshold_c).astype(bool) & (confidence > 0)
    else:
        mask = np.zeros(confidence.shape, bool)
    depth = dsi.depths[index].astype(np.float32)
    depth = _masked_median(depth, mask, median_size) if median_size > 1 else np.where(mask, depth, np.nan)
    rows, cols = np.nonzero(mask)
    pixels = np.column_stack([cols, rows, np.ones(len(rows))]).astype(np.float64)
    points_ref = (pixels @ np.linalg.inv(dsi.K).T) * depth[rows, cols, None].astype(np.float64)
    points_w = points_ref @ dsi.T_w_ref[:3, :3].T + dsi.T_w_ref[:3, 3]
    return SemiDenseDepth(
        depth=depth.astype(np.float32), confidence=confidence, mask=mask, points=points_w,
        t_ref_us=int(dsi.t_ref_us), T_w_ref=dsi.T_w_ref.copy(),
        depth_range=(float(dsi.depths[0]), float(dsi.depths[-1])), n_planes=len(dsi.depths),
        seconds=float(dsi.seconds if seconds is None else seconds), K=dsi.K.copy(), n_events=int(dsi.n_events),
        hot_pixels=dsi.hot_pixels,
    )


def confidence_title(top: float) -> str:
    """Title of the confidence map's grey panel (the DSI's votes; white none): which grey is which (it has no
    colour bar), ``top`` the votes drawn black (the 99th percentile; more saturate). Short: a small sensor's
    panel is narrow.

    >>> confidence_title(291.0)
    'votes: black >= 291'
    """
    return f"votes: black >= {top:.3g}"


def depth_scale_bar(height: int, depth_range: tuple[float, float], *, ticks: int = 5) -> np.ndarray:
    """Vertical colour bar (height, w, 3) BGR of ``depth_range`` [m]: :func:`cmax.viz.depth_colour_bar`."""
    from cmax import viz

    return viz.depth_colour_bar(height, viz.DepthScale(*depth_range), ticks=ticks)


def write_ply(path: str | os.PathLike, points: np.ndarray, *, binary: bool = True) -> Path:
    """Write ``points`` (P, 3) [m] as a PLY file at ``path`` (``binary``: little-endian float32, else ASCII),
    atomically; returns the path."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (P, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points must be finite")
    path = Path(path)
    kind = "binary_little_endian" if binary else "ascii"
    header = (f"ply\nformat {kind} 1.0\ncomment written by cmax.emvs (EMVS semi-dense depth)\n"
              "comment x y z: world frame of the poses (T_w_ref of depth.npz maps the reference camera to it), "
              "in the poses' length unit (metres unless they are up to scale)\n"
              f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    from cmax.io.atomic import write_with  # a lock and a private temporary: no planted link followed

    def fill(output) -> None:
        with os.fdopen(os.dup(output.fd), "wb") as file:
            file.write(header.encode("ascii"))
            if binary:
                file.write(points.astype("<f4").tobytes())
            else:
                np.savetxt(file, points, fmt="%.6f")

    return write_with(path, fill)
