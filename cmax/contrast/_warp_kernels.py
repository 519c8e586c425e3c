"""Compiled se3 warp of one event set with its analytic gradient (the patch refinement's warp).

:func:`cmax.warp.warp_se3` for rays ``r`` (N, 3), times ``dt`` (N,), one twist ``(v, omega)`` and
per-event inverse depths ``rho`` (N,):

    w = omega dt,  s = |w|^2,  A, B, C = rodrigues_coefficients(s)
    P = r + A (w x r) + B (w x (w x r))  +  rho (u + B (w x u) + C (w x (w x u))),   u = v dt
    x = K00 X/Z + K01 Y/Z + K02,   y = K11 Y/Z + K12,   Z = max(P_z, MIN_PROJECTED_DEPTH)

in one pass, and its gradient with respect to ``v``, ``omega`` and ``rho`` in a second pass instead
of torch's two dozen operations and their autograd (which dominate a refinement evaluation once the
patch images are compiled, :mod:`cmax.contrast._patch_kernels`). With ``g = dL/dP`` of an event,

    dL/drho = moved . g
    dL/dv   = rho dt J(w)^T g,    J(w)^T g = g - B (w x g) + C (w x (w x g))
    dL/dw   = 2 A' ((w x r).g) w + A (r x g) + 2 B' ((w x (w x r)).g) w + B ((w x r) x g + r x (g x w))
              + rho [2 B' ((w x u).g) w + B (u x g) + 2 C' ((w x (w x u)).g) w + C ((w x u) x g + u x (g x w))]
    dL/domega = dt dL/dw

where ``A', B', C'`` are the derivatives in ``s``. A clamped ``Z`` passes no gradient to ``P_z``.
Everything is computed in float64 and the positions are returned in the events' dtype: equal to the
torch warp to float rounding (``tests/test_warp_kernels.py``). ``A, B, C`` and their derivatives are
Taylor series in ``s`` where every event turns by less than 1 rad (``_SERIES_MAX_SQ``), which lets the
forward loop run on SIMD registers; elsewhere ``sin`` and ``cos`` as
:func:`cmax.geometry_torch.rodrigues_coefficients` (with its series below ``_SMALL_ANGLE_SQ``). The rays
are passed as (3, N): each coordinate contiguous, as SIMD loads want them.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from cmax._jit import vector_kernel
from cmax.geometry_torch import _SMALL_ANGLE_SQ
from cmax.warp import MIN_PROJECTED_DEPTH

__all__ = ["warp_se3_compiled", "compiled_warp_applies", "project_at_depth", "warp_rotation_compiled"]


def _taylor(first: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The first ``_SERIES_TERMS`` coefficients in ``s`` of ``sum_j (-1)^j s^j / (2j + first)!`` (``A``: first 1,
    ``B``: 2, ``C``: 3) and of its derivative in ``s``."""
    c = [(-1) ** j / math.factorial(2 * j + first) for j in range(_SERIES_TERMS + 1)]
    return tuple(c[:_SERIES_TERMS]), tuple((j + 1) * c[j + 1] for j in range(_SERIES_TERMS))


#: ``A, B, C`` and their derivatives are Taylor series in ``s`` of ``_SERIES_TERMS`` terms wherever every
#: event's ``s = |omega dt|^2 <= _SERIES_MAX_SQ`` (rotations under 1 rad; always, in the fit's windows):
#: the first omitted term is below 2e-20 there, so they equal ``sin`` and ``cos`` to float64 rounding, and
#: the loop, free of calls, runs on SIMD registers. Beyond, ``sin`` and ``cos`` (:func:`_coefficients`).
_SERIES_TERMS, _SERIES_MAX_SQ = 10, 1.0
(_A, _DA), (_B, _DB), (_C, _DC) = _taylor(1), _taylor(2), _taylor(3)


@vector_kernel(inline="always")
def _polynomial(s, c):  # pragma: no cover - compiled
    """``sum_j c[j] s^j`` (Horner) for the ``_SERIES_TERMS`` coefficients ``c``."""
    return c[0] + s * (c[1] + s * (c[2] + s * (c[3] + s * (c[4] + s * (c[5] + s * (c[6] + s * (c[7] + s * (
        c[8] + s * c[9]))))))))


@vector_kernel(inline="always")
def _series(s):  # pragma: no cover - compiled
    """``A, B, C`` and their derivatives in ``s`` by their Taylor series (``s <= _SERIES_MAX_SQ``)."""
    return (_polynomial(s, _A), _polynomial(s, _B), _polynomial(s, _C), _polynomial(s, _DA), _polynomial(s, _DB),
            _polynomial(s, _DC))


@vector_kernel
def _coefficients(s, small):  # pragma: no cover - compiled
    """``A, B, C`` and their derivatives in ``s = theta^2`` by ``sin`` and ``cos`` (any ``s``)."""
    if s < small:
        return (1.0 - s / 6.0 + s * s / 120.0, 0.5 - s / 24.0 + s * s / 720.0, 1.0 / 6.0 - s / 120.0 + s * s / 5040.0,
                -1.0 / 6.0 + s / 60.0, -1.0 / 24.0 + s / 360.0, -1.0 / 120.0 + s / 2520.0)
    t = math.sqrt(s)
    sin, cos = math.sin(t), math.cos(t)
    A, B, C = sin / t, (1.0 - cos) / s, (t - sin) / (s * t)
    dA = (t * cos - sin) / (2.0 * s * t)
    dB = (0.5 * t * sin - (1.0 - cos)) / (s * s)
    dC = ((1.0 - cos) * t - 3.0 * (t - sin)) / (2.0 * s * s * t)
    return A, B, C, dA, dB, dC


@vector_kernel(inline="always")
def _cross(a0, a1, a2, b0, b1, b2):  # pragma: no cover - compiled
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@vector_kernel(inline="always")
def _point(r0, r1, r2, w0, w1, w2, u0, u1, u2, rho, A, B, C):  # pragma: no cover - compiled
    """The warped point ``P`` and the moved part ``J(w) u`` (3 floats each) of a ray, for ``w = omega dt``,
    ``u = v dt`` and the coefficients ``A, B, C`` of ``w``."""
    wr0, wr1, wr2 = _cross(w0, w1, w2, r0, r1, r2)
    wwr0, wwr1, wwr2 = _cross(w0, w1, w2, wr0, wr1, wr2)
    wu0, wu1, wu2 = _cross(w0, w1, w2, u0, u1, u2)
    wwu0, wwu1, wwu2 = _cross(w0, w1, w2, wu0, wu1, wu2)
    m0, m1, m2 = u0 + B * wu0 + C * wwu0, u1 + B * wu1 + C * wwu1, u2 + B * wu2 + C * wwu2
    p0 = r0 + A * wr0 + B * wwr0 + rho * m0
    p1 = r1 + A * wr1 + B * wwr1 + rho * m1
    p2 = r2 + A * wr2 + B * wwr2 + rho * m2
    return p0, p1, p2, m0, m1, m2


@vector_kernel(inline="always")
def _twist_gradient(a0, a1, a2, w0, w1, w2, g0, g1, g2, c1, c2, d1, d2):  # pragma: no cover - compiled
    """``dL/dw`` (3 floats) of ``c1(s) (w x a) + c2(s) (w x (w x a))`` for ``dL/dP = g``, with ``d1, d2`` the
    derivatives of ``c1, c2`` in ``s = |w|^2``: ``2 (d1 (w x a).g + d2 (w x (w x a)).g) w + c1 (a x g)
    + c2 ((w x a) x g + a x (g x w))``."""
    wa0, wa1, wa2 = _cross(w0, w1, w2, a0, a1, a2)
    wwa0, wwa1, wwa2 = _cross(w0, w1, w2, wa0, wa1, wa2)
    ag0, ag1, ag2 = _cross(a0, a1, a2, g0, g1, g2)
    wag0, wag1, wag2 = _cross(wa0, wa1, wa2, g0, g1, g2)
    gw0, gw1, gw2 = _cross(g0, g1, g2, w0, w1, w2)
    agw0, agw1, agw2 = _cross(a0, a1, a2, gw0, gw1, gw2)
    scale = 2.0 * (d1 * (wa0 * g0 + wa1 * g1 + wa2 * g2) + d2 * (wwa0 * g0 + wwa1 * g1 + wwa2 * g2))
    return (scale * w0 + c1 * ag0 + c2 * (wag0 + agw0), scale * w1 + c1 * ag1 + c2 * (wag1 + agw1),
            scale * w2 + c1 * ag2 + c2 * (wag2 + agw2))


@vector_kernel(inline="always")
def _position(r0, r1, r2, t, q, v0, v1, v2, w0, w1, w2, k0, k1, k2, k3, k4, zmin, A, B, C
              ):  # pragma: no cover - compiled
    """``x, y`` (float64) of the ray ``r`` at time ``t`` and inverse depth ``q``, for ``w = omega dt`` and its
    coefficients ``A, B, C``."""
    p0, p1, p2, _, _, _ = _point(r0, r1, r2, w0, w1, w2, v0 * t, v1 * t, v2 * t, q, A, B, C)
    z = max(p2, zmin)
    return k0 * (p0 / z) + k1 * (p1 / z) + k2, k3 * (p1 / z) + k4


@vector_kernel
def _forward(rays, dt, v, omega, rho, k, zmin, series, small, x, y):  # pragma: no cover - compiled
    """``x, y`` (N,) of rays (3, N) (their coordinates in rows); ``series``: every event's ``s`` is at most
    ``_SERIES_MAX_SQ`` (the caller checks). The loops read the twist and ``k`` as scalars (loop invariants
    that no store can change: they vectorise)."""
    v0, v1, v2, o0, o1, o2 = v[0], v[1], v[2], omega[0], omega[1], omega[2]
    k0, k1, k2, k3, k4 = k[0], k[1], k[2], k[3], k[4]
    if series:
        for i in range(dt.shape[0]):
            t = float(dt[i])
            w0, w1, w2 = o0 * t, o1 * t, o2 * t
            A, B, C, _, _, _ = _series(w0 * w0 + w1 * w1 + w2 * w2)
            x[i], y[i] = _position(float(rays[0, i]), float(rays[1, i]), float(rays[2, i]), t, float(rho[i]),
                                   v0, v1, v2, w0, w1, w2, k0, k1, k2, k3, k4, zmin, A, B, C)
    else:
        for i in range(dt.shape[0]):
            t = float(dt[i])
            w0, w1, w2 = o0 * t, o1 * t, o2 * t
            A, B, C, _, _, _ = _coefficients(w0 * w0 + w1 * w1 + w2 * w2, small)
            x[i], y[i] = _position(float(rays[0, i]), float(rays[1, i]), float(rays[2, i]), t, float(rho[i]),
                                   v0, v1, v2, w0, w1, w2, k0, k1, k2, k3, k4, zmin, A, B, C)


@vector_kernel(inline="always")
def _gradient(r0, r1, r2, t, q, v0, v1, v2, w0, w1, w2, k0, k1, k3, zmin, ax, ay, twist, A, B, C, dA, dB, dC
              ):  # pragma: no cover - compiled
    """``dL/drho`` of one event (the ray ``r`` at time ``t``, inverse depth ``q``) and its terms of ``dL/dv``,
    ``dL/domega`` (3 floats each; zero without ``twist``) for ``dL/dx = ax``, ``dL/dy = ay``, the
    coefficients of its ``w = omega dt`` and their derivatives."""
    u0, u1, u2 = v0 * t, v1 * t, v2 * t
    p0, p1, p2, m0, m1, m2 = _point(r0, r1, r2, w0, w1, w2, u0, u1, u2, q, A, B, C)
    clamped = p2 < zmin
    z = zmin if clamped else p2
    g0 = ax * k0 / z
    g1 = (ax * k1 + ay * k3) / z
    g2 = 0.0 if clamped else -(ax * (k0 * p0 + k1 * p1) + ay * k3 * p1) / (z * z)
    grad_rho = m0 * g0 + m1 * g1 + m2 * g2
    if not twist:
        return grad_rho, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    # dL/dv = rho dt J^T g
    wg0, wg1, wg2 = _cross(w0, w1, w2, g0, g1, g2)
    wwg0, wwg1, wwg2 = _cross(w0, w1, w2, wg0, wg1, wg2)
    f = q * t
    # dL/dw: the rotated ray's terms, then rho times the moved part's (the same form in u = v dt)
    d0, d1, d2 = _twist_gradient(r0, r1, r2, w0, w1, w2, g0, g1, g2, A, B, dA, dB)
    e0, e1, e2 = _twist_gradient(u0, u1, u2, w0, w1, w2, g0, g1, g2, B, C, dB, dC)
    return (grad_rho, f * (g0 - B * wg0 + C * wwg0), f * (g1 - B * wg1 + C * wwg1), f * (g2 - B * wg2 + C * wwg2),
            t * (d0 + q * e0), t * (d1 + q * e1), t * (d2 + q * e2))


@vector_kernel(fastmath={"reassoc"})
def _backward_terms(rays, dt, v, omega, rho, k, zmin, series, small, gx, gy, grad_rho, terms, twist
                    ):  # pragma: no cover - compiled
    """``grad_rho`` (N,) for ``dL/dx = gx``, ``dL/dy = gy`` (N,), and each event's six terms of ``dL/dv``,
    ``dL/domega`` in ``terms`` (6, N) (zeros without ``twist``; :func:`_sum_terms` adds them). Rays and
    ``series`` as :func:`_forward`: with ``series`` the loop holds no call and no reduction, so it runs on
    SIMD registers (reassociation is allowed within an event's terms; the sums over events are
    :func:`_sum_terms`'s, in event order)."""
    v0, v1, v2, o0, o1, o2 = v[0], v[1], v[2], omega[0], omega[1], omega[2]
    k0, k1, k3 = k[0], k[1], k[3]
    if series:
        for i in range(dt.shape[0]):
            t = float(dt[i])
            w0, w1, w2 = o0 * t, o1 * t, o2 * t
            A, B, C, dA, dB, dC = _series(w0 * w0 + w1 * w1 + w2 * w2)
            grad_rho[i], terms[0, i], terms[1, i], terms[2, i], terms[3, i], terms[4, i], terms[5, i] = _gradient(
                float(rays[0, i]), float(rays[1, i]), float(rays[2, i]), t, float(rho[i]), v0, v1, v2, w0, w1, w2,
                k0, k1, k3, zmin, float(gx[i]), float(gy[i]), twist, A, B, C, dA, dB, dC)
    else:
        for i in range(dt.shape[0]):
            t = float(dt[i])
            w0, w1, w2 = o0 * t, o1 * t, o2 * t
            A, B, C, dA, dB, dC = _coefficients(w0 * w0 + w1 * w1 + w2 * w2, small)
            grad_rho[i], terms[0, i], terms[1, i], terms[2, i], terms[3, i], terms[4, i], terms[5, i] = _gradient(
                float(rays[0, i]), float(rays[1, i]), float(rays[2, i]), t, float(rho[i]), v0, v1, v2, w0, w1, w2,
                k0, k1, k3, zmin, float(gx[i]), float(gy[i]), twist, A, B, C, dA, dB, dC)


@vector_kernel
def _sum_terms(terms, grad_v, grad_omega):  # pragma: no cover - compiled
    """``grad_v``, ``grad_omega`` (3,) += the rows of ``terms`` (6, N), each summed in event order (compiled
    without reassociation, so the order is the loop's)."""
    s0, s1, s2, s3, s4, s5 = grad_v[0], grad_v[1], grad_v[2], grad_omega[0], grad_omega[1], grad_omega[2]
    for i in range(terms.shape[1]):
        s0, s1, s2 = s0 + terms[0, i], s1 + terms[1, i], s2 + terms[2, i]
        s3, s4, s5 = s3 + terms[3, i], s4 + terms[4, i], s5 + terms[5, i]
    grad_v[0], grad_v[1], grad_v[2], grad_omega[0], grad_omega[1], grad_omega[2] = s0, s1, s2, s3, s4, s5


def _arrays(rays, dt, v, omega, rho, K):
    def flat(tensor, dtype=np.float64):
        return np.ascontiguousarray(tensor.detach().numpy(), dtype=dtype)

    return (np.ascontiguousarray(rays.detach().numpy().T), np.ascontiguousarray(dt.detach().numpy()), flat(v),
            flat(omega), np.ascontiguousarray(rho.detach().numpy()), intrinsics_row(flat(K)))


def intrinsics_row(K: np.ndarray) -> np.ndarray:
    """``(K00, K01, K02, K11, K12)`` (5,) float64 of ``K`` (3, 3): what the kernels read."""
    return np.array([K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]], dtype=np.float64)


def _within_series(dt: np.ndarray, omega: np.ndarray, dt_max: float | None) -> bool:
    """Whether every event's ``s = |omega dt|^2`` is at most ``_SERIES_MAX_SQ`` (``dt_max``: ``max |dt|``
    when the caller knows it)."""
    if dt.shape[0] == 0:
        return True
    reach = float(np.abs(dt).max()) if dt_max is None else dt_max
    return float(np.dot(omega, omega)) * reach * reach <= _SERIES_MAX_SQ


def se3_warp_arrays(rays: np.ndarray, dt: np.ndarray, v: np.ndarray, omega: np.ndarray, rho: np.ndarray,
                    k: np.ndarray, dt_max: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The warp of the module docstring on contiguous arrays: ``rays`` (3, N) (the rays' coordinates in
    rows), ``dt``, ``rho`` (N,) of one float dtype, ``v``, ``omega`` (3,) float64, ``k`` from
    :func:`intrinsics_row`, ``dt_max`` ``max |dt|`` [s] if known; ``x, y`` (N,) in that dtype."""
    x = np.empty(dt.shape[0], rays.dtype)
    y = np.empty_like(x)
    _forward(rays, dt, v, omega, rho, k, MIN_PROJECTED_DEPTH, _within_series(dt, omega, dt_max), _SMALL_ANGLE_SQ,
             x, y)
    return x, y


def se3_warp_gradients(rays: np.ndarray, dt: np.ndarray, v: np.ndarray, omega: np.ndarray, rho: np.ndarray,
                       k: np.ndarray, gx: np.ndarray, gy: np.ndarray, twist: bool = True, dt_max: float | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``dL/dv`` (3,), ``dL/domega`` (3,) float64 (zero without ``twist``) and ``dL/drho`` (N,) float64 of the
    warp of :func:`se3_warp_arrays` for ``dL/dx = gx``, ``dL/dy = gy`` (N,)."""
    grad_v, grad_omega, grad_rho = np.zeros(3), np.zeros(3), np.empty(dt.shape[0])
    terms = np.empty((6, dt.shape[0]))
    _backward_terms(rays, dt, v, omega, rho, k, MIN_PROJECTED_DEPTH, _within_series(dt, omega, dt_max),
                    _SMALL_ANGLE_SQ, gx, gy, grad_rho, terms, twist)
    if twist:
        _sum_terms(terms, grad_v, grad_omega)
    return grad_v, grad_omega, grad_rho


@vector_kernel
def project_at_depth(rotated, moved, rho, k, zmin, x, y):  # pragma: no cover - compiled
    """``x, y = project(rotated + rho moved)`` (N,) for the two depth-free parts (N, 3) of the warp
    (:func:`cmax.warp.se3_parts`) and inverse depths ``rho`` (N,), all in one dtype, as
    :func:`cmax.warp.project` computes it in that dtype (``k`` (5,) and ``zmin`` of it too): one pass per
    candidate of a depth sweep instead of torch's eight."""
    for i in range(rotated.shape[0]):
        q = rho[i]
        p0 = rotated[i, 0] + q * moved[i, 0]
        p1 = rotated[i, 1] + q * moved[i, 1]
        z = max(rotated[i, 2] + q * moved[i, 2], zmin)
        X, Y = p0 / z, p1 / z
        x[i] = k[0] * X + k[1] * Y + k[2]
        y[i] = k[3] * Y + k[4]


class _Se3Warp(torch.autograd.Function):
    """:func:`warp_se3_compiled` with its compiled backward."""

    @staticmethod
    def forward(ctx, rays, dt, v, omega, rho, K):  # type: ignore[override]
        arrays = _arrays(rays, dt, v, omega, rho, K)
        ctx.arrays, ctx.dtypes = arrays, (v.dtype, omega.dtype, rho.dtype)
        x, y = se3_warp_arrays(*arrays)
        return torch.from_numpy(x), torch.from_numpy(y)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_x, grad_y):  # type: ignore[override]
        arrays = ctx.arrays
        n = arrays[1].shape[0]
        gx = np.zeros(n) if grad_x is None else np.ascontiguousarray(grad_x.numpy())
        gy = np.zeros(n) if grad_y is None else np.ascontiguousarray(grad_y.numpy())
        needs = ctx.needs_input_grad
        grad_v, grad_omega, grad_rho = se3_warp_gradients(*arrays, gx, gy, bool(needs[2] or needs[3]))
        v_dtype, omega_dtype, rho_dtype = ctx.dtypes
        return (None, None, torch.from_numpy(grad_v).to(v_dtype) if needs[2] else None,
                torch.from_numpy(grad_omega).to(omega_dtype) if needs[3] else None,
                torch.from_numpy(grad_rho).to(rho_dtype) if needs[4] else None, None)


def compiled_warp_applies(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor,
                          rho: torch.Tensor) -> bool:
    """Whether :func:`warp_se3_compiled` takes these inputs: CPU float32/float64 rays (N, 3), ``dt`` and
    ``rho`` (N,) of the same dtype, ``v`` and ``omega`` (3,) (any float dtype), and neither the rays nor
    ``dt`` needing a gradient (the kernel gives none for them: event pixels or intrinsics being learned
    take the torch warp)."""
    n = rays.shape[0] if rays.dim() == 2 else -1
    tensors = (rays, dt, v, omega, rho)
    return (all(t.device.type == "cpu" for t in tensors) and rays.dtype in (torch.float32, torch.float64)
            and not rays.requires_grad and not dt.requires_grad
            and rays.shape == (n, 3) and dt.shape == (n,) and rho.shape == (n,) and dt.dtype == rays.dtype
            and rho.dtype == rays.dtype and v.shape == (3,) and omega.shape == (3,)
            and v.is_floating_point() and omega.is_floating_point())


def warp_se3_compiled(rays: torch.Tensor, dt: torch.Tensor, v: torch.Tensor, omega: torch.Tensor,
                      rho: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cmax.warp.warp_se3` for one event set (see the module docstring); differentiable in ``v``,
    ``omega`` and ``rho`` (first order).

    Parameters
    ----------
    rays : Tensor (N, 3), float32 or float64, CPU
        ``K^-1 (x, y, 1)`` of the events.
    dt : Tensor (N,), the dtype of ``rays``
        ``t_i - t_ref`` [s].
    v, omega : Tensor (3,)
        Linear [m/s] and angular [rad/s] velocity, camera frame.
    rho : Tensor (N,), the dtype of ``rays``
        Inverse depth of each event [1/m].
    K : Tensor (3, 3)

    Returns
    -------
    x, y : Tensor (N,), the dtype of ``rays``
    """
    if not compiled_warp_applies(rays, dt, v, omega, rho):
        raise ValueError("warp_se3_compiled needs CPU float32/float64 rays (N, 3), dt and rho (N,) of their dtype "
                         "(rays and dt without a gradient) and v, omega (3,); got {tuple(rays.shape)} {rays.dtype}, {tuple(dt.shape)} {dt.dtype}, "
                         f"{tuple(rho.shape)} {rho.dtype}, {tuple(v.shape)}, {tuple(omega.shape)}")
    return _Se3Warp.apply(rays, dt, v, omega, rho, K)


def warp_rotation_compiled(rays: torch.Tensor, dt: torch.Tensor, omega: torch.Tensor, K: torch.Tensor
                           ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """:func:`cmax.warp.warp_rotation` by :func:`warp_se3_compiled` with no translation (``v = 0``, ``rho = 0``),
    row by row for ``dt`` (N,) or (R, N): equal to the torch warp to float rounding, differentiable in
    ``omega``; None when the compiled warp does not take these inputs (:func:`compiled_warp_applies`)."""
    zero, rho = rays.new_zeros(3), rays.new_zeros(rays.shape[0] if rays.dim() == 2 else 0)
    rows = dt if dt.dim() == 2 else dt[None]
    if not all(compiled_warp_applies(rays, row, zero, omega, rho) for row in rows):
        return None
    xs, ys = zip(*(warp_se3_compiled(rays, row, zero, omega, rho, K) for row in rows))
    x, y = torch.stack(xs), torch.stack(ys)
    return (x, y) if dt.dim() == 2 else (x[0], y[0])
