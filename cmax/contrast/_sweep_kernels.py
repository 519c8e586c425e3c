"""Compiled kernels of the depth sweep's cost (:class:`cmax.contrast.SweepNodeCost`) on the CPU.

The same arithmetic as the torch reference of :mod:`cmax.contrast.sweep`, operation for operation and in
the events' own float dtype (float32 or float64), so the two agree to float rounding (bit for bit where the
order of the sums is the same):

* the se3 warp of :func:`cmax.warp.warp_se3`: ``rotated + rho moved`` per candidate, its z clamped to
  :data:`cmax.warp.MIN_PROJECTED_DEPTH`, projected with ``K`` (``rotated`` and ``moved`` do not depend on
  the inverse depth: torch computes them once per call too, :func:`se3_terms`);
* the bilinear votes of :func:`cmax.iwe._splat` (a point whose lower-left pixel lies outside
  ``[-1, W-1] x [-1, H-1]`` votes nothing; corners off the image are dropped), added corner by corner in
  event order, as ``index_add`` adds them;
* the read-back of :func:`cmax.iwe.sample_bilinear` (zero outside, same validity rule), of each event's
  own polarity image only (the other image enters the reference's score times 0);
* the per-node sums of the normalised votes in event order, as ``index_add_`` along the node axis.

The Gaussian blur between votes and read-back stays OpenCV's ``sepFilter2D`` (zero padding), as in
:func:`cmax.iwe.blur` on the CPU. Scalars enter the kernels in the events' dtype (``one``, ``zmin``, the
entries of ``K``) so that numba keeps float32 arithmetic in float32; the kernels use numba's ``numpy``
error model (IEEE division, as torch, without Python's zero-division check, which would stop the
vectorisation of the warp).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from cmax._jit import kernel
from cmax.geometry_torch import rodrigues_coefficients
from cmax.iwe import _gaussian_kernel
from cmax.warp import MIN_PROJECTED_DEPTH

__all__ = ["se3_terms", "event_scores_compiled", "vote_scale_compiled", "node_sums"]


def se3_terms(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The two depth-independent parts of :func:`cmax.warp.warp_se3`: ``R(omega dt) ray`` and
    ``J(omega dt) v dt``, each (N, 3) in the dtype of ``rays``, by the same torch operations (so that
    ``project(rotated + rho moved, K)`` is the reference warp bit for bit).

    ``rays`` (N, 3), ``dt`` (N,) or (1, N) [s], ``v`` (3,) [m/s], ``omega`` (3,) [rad/s].
    """
    dt = dt.reshape(1, -1)
    w = omega * dt[..., None]
    shape = w.shape
    rays = rays.expand(shape)
    A, B, C = rodrigues_coefficients((w * w).sum(-1, keepdim=True))
    wr = torch.linalg.cross(w, rays, dim=-1)
    rotated = rays + A * wr + B * torch.linalg.cross(w, wr, dim=-1)
    u = (v * dt[..., None]).expand(shape)
    wu = torch.linalg.cross(w, u, dim=-1)
    moved = u + B * wu + C * torch.linalg.cross(w, wu, dim=-1)
    return rotated[0], moved[0]


@kernel(error_model="numpy")
def _warp(rotated, moved, rho, k00, k01, k02, k11, k12, zmin, width, height, border, one, base, fx, fy,
          inside):  # pragma: no cover - compiled
    """Warp every event with each row of ``rho`` (C, N) [1/m] (:func:`cmax.warp.warp_se3`).

    Writes, per candidate and event (C, N): ``base``, the flat index of the lower-left pixel in an image
    padded by one pixel on each side ((H + 2) x (W + 2)), -1 where the event votes and reads nothing;
    ``fx``, ``fy``, the position's fractional part; ``inside``, 1 where it lies ``border`` px inside the
    image, else 0. ``rotated``, ``moved`` (N, 3).
    """
    C, N = rho.shape
    Wp = width + 2
    zero = one - one
    for c in range(C):
        for n in range(N):
            r = rho[c, n]
            px = rotated[n, 0] + r * moved[n, 0]
            py = rotated[n, 1] + r * moved[n, 1]
            z = rotated[n, 2] + r * moved[n, 2]
            if z < zmin:
                z = zmin
            X = px / z
            Y = py / z
            x = k00 * X + k01 * Y + k02
            y = k11 * Y + k12
            inside[c, n] = one if (x >= border and x <= width - 1 - border and y >= border
                                   and y <= height - 1 - border) else zero
            x0, y0 = np.floor(x), np.floor(y)
            fx[c, n], fy[c, n] = x - x0, y - y0
            if x0 >= -1 and x0 <= width - 1 and y0 >= -1 and y0 <= height - 1:
                base[c, n] = (int(y0) + 1) * Wp + int(x0) + 1
            else:
                base[c, n] = -1


@kernel(error_model="numpy")
def _splat(base, fx, fy, image_of, Wp, one, canvas):  # pragma: no cover - compiled
    """Bilinear votes of the warped events into ``canvas`` (C, P, (H + 2) Wp) (zeros on entry; the
    padding collects the votes that fall off the image), corner after corner in event order as
    ``index_add`` adds the stacked corners of :func:`cmax.iwe._splat`."""
    C, N = base.shape
    for c in range(C):
        for n in range(N):
            b = base[c, n]
            if b >= 0:
                canvas[c, image_of[n], b] += (one - fx[c, n]) * (one - fy[c, n])
        for n in range(N):
            b = base[c, n]
            if b >= 0:
                canvas[c, image_of[n], b + 1] += fx[c, n] * (one - fy[c, n])
        for n in range(N):
            b = base[c, n]
            if b >= 0:
                canvas[c, image_of[n], b + Wp] += (one - fx[c, n]) * fy[c, n]
        for n in range(N):
            b = base[c, n]
            if b >= 0:
                canvas[c, image_of[n], b + Wp + 1] += fx[c, n] * fy[c, n]


@kernel(error_model="numpy")
def _sample_own(images, base, fx, fy, image_of, inside, Wp, one, score, peak, always):  # pragma: no cover
    """Each event's bilinear read (C, N) of its own polarity image in ``images`` (C, P, (H + 2) Wp), zero
    padded, at its warped position (:func:`cmax.iwe.sample_bilinear`; 0 where ``base`` is -1), and the
    running per-event largest ``score * inside`` (``peak`` (N,)) and whether the event stayed inside for
    every candidate so far (``always`` (N,) bool)."""
    C, N = base.shape
    zero = one - one
    for c in range(C):
        for n in range(N):
            b = base[c, n]
            if b < 0:
                value = zero
            else:
                image = images[c, image_of[n]]
                u, v = fx[c, n], fy[c, n]
                value = ((one - u) * (one - v) * image[b] + u * (one - v) * image[b + 1]
                         + (one - u) * v * image[b + Wp] + u * v * image[b + Wp + 1])
            score[c, n] = value
            held = value * inside[c, n]
            if held > peak[n]:
                peak[n] = held
            if inside[c, n] <= zero:
                always[n] = False


@kernel(error_model="numpy")
def _node_sums(score, scale, inside, index, weight, sums, weights):  # pragma: no cover - compiled
    """Add ``inside * weight * score / scale`` and ``inside * weight`` of every event into its four
    nodes: ``sums``, ``weights`` (C, G) (zeros on entry); ``index``, ``weight`` (N, 4), ``scale`` (N,)."""
    C, N = score.shape
    for c in range(C):
        for n in range(N):
            s = score[c, n] / scale[n]
            for k in range(4):
                w = inside[c, n] * weight[n, k]
                g = index[n, k]
                sums[c, g] += w * s
                weights[c, g] += w


def event_scores_compiled(rotated: np.ndarray, moved: np.ndarray, rho: np.ndarray, image_of: np.ndarray,
                          images: int, K: np.ndarray, height: int, width: int, sigma: float, border_px: int,
                          chunk: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cmax.contrast.sweep.event_scores` for all candidates by the kernels of this module: the IWE
    value at each event's warped position and the inside flag, both (C, N) in ``rho``'s dtype, and per
    event (N,) the largest ``score * inside`` over the candidates and whether every candidate keeps the
    event inside (bool).

    ``rotated``, ``moved`` (N, 3) from :func:`se3_terms`; ``rho`` (C, N) [1/m]; ``image_of`` (N,) int64
    (0: first polarity image, 1: second); ``images``: 2 with a polarity split, else 1; ``K`` (3, 3);
    blur ``sigma`` [px]; ``chunk`` candidates warped at once (memory only: no effect on the result).
    """
    dtype = rho.dtype.type
    C, N = rho.shape
    k = K.astype(rho.dtype)
    torch_dtype = torch.from_numpy(rho[:0, :0]).dtype
    taps = _gaussian_kernel(float(sigma), torch_dtype, torch.device("cpu")).numpy() if sigma > 0 else None
    Hp, Wp = height + 2, width + 2
    score, inside = np.empty((C, N), rho.dtype), np.empty((C, N), rho.dtype)
    peak, always = np.full(N, -np.inf, rho.dtype), np.ones(N, np.bool_)
    chunk = max(1, min(int(chunk), C))
    canvas = np.empty((chunk, images, Hp * Wp), rho.dtype)
    blurred = np.zeros_like(canvas)                     # the padding stays zero: only the interior is written
    base = np.empty((chunk, N), np.int64)
    fx, fy = np.empty((chunk, N), rho.dtype), np.empty((chunk, N), rho.dtype)
    for start in range(0, C, chunk):
        stop = min(C, start + chunk)
        m = stop - start
        _warp(rotated, moved, rho[start:stop], k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2],
              dtype(MIN_PROJECTED_DEPTH), width, height, border_px, dtype(1), base[:m], fx[:m], fy[:m],
              inside[start:stop])
        canvas[:m] = 0
        _splat(base[:m], fx[:m], fy[:m], image_of, Wp, dtype(1), canvas[:m])
        if taps is None:
            seen = canvas
        else:
            for i in range(m):
                for p in range(images):
                    cv2.sepFilter2D(canvas[i, p].reshape(Hp, Wp)[1:-1, 1:-1], -1, taps, taps,
                                    dst=blurred[i, p].reshape(Hp, Wp)[1:-1, 1:-1], borderType=cv2.BORDER_CONSTANT)
            seen = blurred
        _sample_own(seen[:m], base[:m], fx[:m], fy[:m], image_of, inside[start:stop], Wp, dtype(1),
                    score[start:stop], peak, always)
    return score, inside, peak, always


def vote_scale_compiled(peak: np.ndarray, always: np.ndarray, quantile: float) -> np.ndarray:
    """:func:`cmax.contrast.sweep.vote_scale` from the per-event ``peak`` and ``always`` (N,) of
    :func:`event_scores_compiled`: (N,), the same values (the quantile by selection, not a sort)."""
    pool = peak[always] if always.any() else peak
    kth = int((pool.size - 1) * quantile)
    typical = np.partition(pool, kth)[kth]
    return np.maximum(np.where(always, peak, typical), peak.dtype.type(1e-12))


def node_sums(score: np.ndarray, scale: np.ndarray, inside: np.ndarray, index: np.ndarray, weight: np.ndarray,
              nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-node sums (C, G) of ``inside * weight * score / scale`` and of ``inside * weight``: the
    ``index_add_`` of :class:`cmax.contrast.SweepNodeCost`, in ``score``'s dtype.

    ``score``, ``inside`` (C, N); ``scale`` (N,); ``index`` (N, 4) int64 node indices < ``nodes``;
    ``weight`` (N, 4).
    """
    sums = np.zeros((score.shape[0], nodes), score.dtype)
    weights = np.zeros_like(sums)
    _node_sums(score, scale, inside, index, weight, sums, weights)
    return sums, weights
