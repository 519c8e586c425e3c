"""Compiled kernels of the depth sweep's cost (:class:`cmax.contrast.SweepNodeCost`) on the CPU.

The same arithmetic as the torch reference of :mod:`cmax.contrast.sweep`, operation for operation, in
the events' own float dtype (float32 or float64), with every sum taken in the order in which torch's CPU
``index_add`` takes it (one thread), so the two agree bit for bit on the tested windows (and to float
rounding should torch's order change):

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
error model (IEEE division, as torch, with no zero-division check in the loops).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from cmax._jit import vector_kernel
from cmax.iwe import _gaussian_kernel
from cmax.warp import MIN_PROJECTED_DEPTH, se3_parts

__all__ = ["se3_terms", "event_scores_compiled", "vote_scale_compiled", "node_sums"]


def se3_terms(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The two depth-independent parts of :func:`cmax.warp.warp_se3` (:func:`cmax.warp.se3_parts`, the
    same torch operations, so that ``project(rotated + rho moved, K)`` is the reference warp bit for bit):
    ``R(omega dt) ray`` and ``J(omega dt) v dt``, each (N, 3) in the dtype of ``rays``.

    ``rays`` (N, 3), ``dt`` (N,) or (1, N) [s], ``v`` (3,) [m/s], ``omega`` (3,) [rad/s].
    """
    rotated, moved = se3_parts(rays, dt.reshape(1, -1), v, omega)
    return rotated[0], moved[0]


@vector_kernel
def _warp(rotated, moved, rho, offset, k00, k01, k02, k11, k12, zmin, width, height, border, one, base, fx, fy,
          inside):  # pragma: no cover - compiled
    """Warp every event with each row of ``rho`` (C, N) [1/m] (:func:`cmax.warp.warp_se3`).

    ``rotated``, ``moved`` (3, N); ``offset`` (N,) int: where the event's polarity image starts in a
    stack of images padded by one pixel on each side ((H + 2) x (W + 2) each). Writes, per candidate and
    event (C, N): ``base`` (int), the flat index in that stack of the lower-left pixel of the warped
    position, -1 where the event votes and reads nothing (:func:`cmax.iwe._splat`'s rule); ``fx``,
    ``fy``, the position's fractional part; ``inside``, 1 where it lies ``border`` px inside the image,
    else 0.
    """
    C, N = rho.shape
    Wp = width + 2
    zero = one - one
    for c in range(C):
        for n in range(N):
            r = rho[c, n]
            px = rotated[0, n] + r * moved[0, n]
            py = rotated[1, n] + r * moved[1, n]
            z = rotated[2, n] + r * moved[2, n]
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
                base[c, n] = offset[n] + (int(y0) + 1) * Wp + int(x0) + 1
            else:
                base[c, n] = -1


@vector_kernel
def _splat(base, fx, fy, Wp, one, canvas):  # pragma: no cover - compiled
    """Bilinear votes of the warped events into ``canvas`` (C, P (H + 2) Wp) (zeros on entry; the
    padding collects the votes that fall off the image), corner after corner in event order as
    ``index_add`` adds the stacked corners of :func:`cmax.iwe._splat`."""
    C, N = base.shape
    for c in range(C):
        image, b_, u_, v_ = canvas[c], base[c], fx[c], fy[c]
        for n in range(N):
            if b_[n] >= 0:
                image[b_[n]] += (one - u_[n]) * (one - v_[n])
        for n in range(N):
            if b_[n] >= 0:
                image[b_[n] + 1] += u_[n] * (one - v_[n])
        for n in range(N):
            if b_[n] >= 0:
                image[b_[n] + Wp] += (one - u_[n]) * v_[n]
        for n in range(N):
            if b_[n] >= 0:
                image[b_[n] + Wp + 1] += u_[n] * v_[n]


@vector_kernel
def _sample_own(images, base, fx, fy, inside, Wp, one, score, peak, always):  # pragma: no cover - compiled
    """Each event's bilinear read (C, N) of its own polarity image in ``images`` (C, P (H + 2) Wp), zero
    padded, at its warped position (:func:`cmax.iwe.sample_bilinear`; 0 where ``base`` is -1), and the
    running per-event largest ``score * inside`` (``peak`` (N,)) and whether the event stayed inside for
    every candidate so far (``always`` (N,) bool)."""
    C, N = base.shape
    zero = one - one
    for c in range(C):
        image = images[c]
        for n in range(N):
            b = base[c, n]
            if b < 0:
                value = zero
            else:
                u, v = fx[c, n], fy[c, n]
                value = ((one - u) * (one - v) * image[b] + u * (one - v) * image[b + 1]
                         + (one - u) * v * image[b + Wp] + u * v * image[b + Wp + 1])
            score[c, n] = value
            if inside[c, n] > zero:
                if value > peak[n]:      # value * 1
                    peak[n] = value
            else:
                always[n] = False
                if zero > peak[n]:       # value * 0
                    peak[n] = zero


@vector_kernel
def _node_sums(score, scale, inside, index, weight, sums, weights):  # pragma: no cover - compiled
    """Add ``inside * weight * score / scale`` and ``inside * weight`` of every event into its four
    nodes: ``sums``, ``weights`` (C, G) (zeros on entry); ``index``, ``weight`` (N, 4), ``scale`` (N,).
    ``inside`` is 1 or 0: an event outside adds zeros, and is skipped."""
    C, N = score.shape
    zero = scale[0] - scale[0]
    for c in range(C):
        for n in range(N):
            if not inside[c, n] > zero:
                continue
            s = score[c, n] / scale[n]
            for k in range(4):
                w = inside[c, n] * weight[n, k]
                g = index[n, k]
                sums[c, g] += w * s
                weights[c, g] += w


def event_scores_compiled(rotated: np.ndarray, moved: np.ndarray, rho: np.ndarray, image_of: np.ndarray,
                          images: int, K: np.ndarray, height: int, width: int, sigma: float, border_px: int,
                          chunk: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`cmax.contrast.sweep.event_scores` for all candidates by the kernels of this module: the IWE
    value at each event's warped position and the inside flag, both (C, N) in ``rho``'s dtype, and per
    event (N,) the largest ``score * inside`` over the candidates and whether every candidate keeps the
    event inside (bool).

    ``rotated``, ``moved`` (N, 3) from :func:`se3_terms`; ``rho`` (C, N) [1/m]; ``image_of`` (N,) int64
    (0: first polarity image, 1: second); ``images``: 2 with a polarity split, else 1; ``K`` (3, 3);
    blur ``sigma`` [px]; ``chunk`` candidates warped at once (no effect on the result; one at a time keeps
    a candidate's images in the cache from the votes to the read-back).
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
    canvas = np.empty((chunk, images * Hp * Wp), rho.dtype)
    blurred = np.zeros_like(canvas)                     # the padding stays zero: only the interior is written
    index_type = np.int32 if images * Hp * Wp < 2**31 - 1 else np.int64
    base = np.empty((chunk, N), index_type)
    fx, fy = np.empty((chunk, N), rho.dtype), np.empty((chunk, N), rho.dtype)
    offset = (image_of * (Hp * Wp)).astype(index_type)
    rotated_t, moved_t = np.ascontiguousarray(rotated.T), np.ascontiguousarray(moved.T)
    for start in range(0, C, chunk):
        stop = min(C, start + chunk)
        m = stop - start
        _warp(rotated_t, moved_t, rho[start:stop], offset, k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2],
              dtype(MIN_PROJECTED_DEPTH), width, height, border_px, dtype(1), base[:m], fx[:m], fy[:m],
              inside[start:stop])
        canvas[:m] = 0
        _splat(base[:m], fx[:m], fy[:m], Wp, dtype(1), canvas[:m])
        if taps is None:
            seen = canvas
        else:
            for i in range(m):
                for p in range(images):
                    source = canvas[i].reshape(images, Hp, Wp)[p, 1:-1, 1:-1]
                    target = blurred[i].reshape(images, Hp, Wp)[p, 1:-1, 1:-1]
                    cv2.sepFilter2D(source, -1, taps, taps, dst=target, borderType=cv2.BORDER_CONSTANT)
            seen = blurred
        _sample_own(seen[:m], base[:m], fx[:m], fy[:m], inside[start:stop], Wp, dtype(1), score[start:stop],
                    peak, always)
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
