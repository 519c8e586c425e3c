"""Initial translation direction and rotation from patch flows and the motion-field equations.

The image is cut into patches; each patch gets a constant optical flow by
contrast maximization of its own events (all patches in one solve: the
objective is the sum of the patches' normalised IWE variances, separable:
the contrast core's :class:`cmax.contrast.patches.PatchFlowContrast`),
first with a wide blur (a wide basin), then with the window's blur. The
curvature of each patch's contrast at its peak (:func:`flow_information`)
says how well its flow is known: a patch that sees one edge orientation
knows only the flow across it (the aperture problem).
The instantaneous motion field of a rigid scene is, at pixel ``x`` with
inverse depth ``rho``,

    u(x) = rho A(x) v + B(x) omega                    (Longuet-Higgins & Prazdny, 1980)

with ``A`` and ``B`` (2 x 3) read off the se3 warp of :mod:`cmax.warp` by
finite differences (so the sign conventions are the warp's own). For a
candidate direction ``t`` (``v = speed t``) the patch flows are linear in
``omega`` and the patches' ``rho``: one least-squares problem per direction,
each patch's residual weighted by its information matrix, solved for a few
thousand directions on the sphere at once and then in a fine cap around the
best; the direction with the smallest residual whose inverse depths are
mostly positive wins.

This is the se3 initialiser (:class:`cmax.fitting.pipeline.PatchFlowStage`);
:mod:`cmax.fitting.motion` refines it. Why two blurs, the margin and the
information weights: ``docs/fitting.md``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from cmax.contrast.patches import Patches, PatchFlowContrast, cut_patches
from cmax.fitting.settings import PatchFlowSettings
from cmax.fitting.solvers import GradientLoss, ScipySolver, Solver, SolveResult, solve
from cmax.warp import warp_se3

__all__ = ["Patches", "PatchFlows", "make_patches", "patch_flows", "flow_information", "motion_from_flows",
           "explain_flows",
           "spherical_cap", "fibonacci_sphere"]


def make_patches(w, *, grid: tuple[int, int], min_events: int, max_events: int, margin: float,
                 min_margin_px: int = 8) -> Patches | None:
    """Cut a window's events (``w``: a :class:`cmax.fitting.window.Window`) into a ``grid`` (rows, cols) of
    patches (:func:`cmax.contrast.patches.cut_patches`); None when no patch has ``min_events``."""
    ev = w.ev
    return cut_patches(ev.x, ev.y, w.dt_mid[0], ev.width, ev.height, grid=grid, min_events=min_events,
                       max_events=max_events, margin=margin, min_margin_px=min_margin_px)


def _flow_loss(patches: Patches, sigma: float, T: float) -> PatchFlowContrast:
    """``loss(q (2P,) float64) -> scalar``: minus the summed normalised IWE variances of the patches
    (:class:`cmax.contrast.patches.PatchFlowContrast`); ``q`` holds each patch's displacement over the
    window [px] (flow times ``T`` [s])."""
    return PatchFlowContrast.build(patches, sigma, T)


def flow_information(fun_and_grad, q: np.ndarray, step: float = 0.25, floor: float = 1e-3) -> np.ndarray:
    """Curvature (P, 2, 2) [1/px^2] of each patch's contrast peak: how sharply its flow is determined.

    Minus the Hessian of the normalised contrast with respect to the patch's
    displacement ``q`` (P, 2) [px], by central differences of the gradient
    (``step`` [px]), symmetrised, its eigenvalues clipped to at least ``floor``
    times the largest over all patches. An edge of one orientation gives a rank-one
    matrix (the aperture problem): its flow along the edge is free.
    """
    P = q.shape[0]
    H = np.zeros((P, 2, 2))
    for j in range(2):
        e = np.zeros((P, 2))
        e[:, j] = step
        plus, minus = fun_and_grad((q + e).reshape(-1))[1], fun_and_grad((q - e).reshape(-1))[1]
        H[:, :, j] = (plus - minus).reshape(P, 2) / (2 * step)   # fun is minus the contrast
    H = 0.5 * (H + H.transpose(0, 2, 1))
    values, vectors = np.linalg.eigh(H)
    values = np.clip(values, floor * max(float(values.max()), 1e-12), None)
    return np.einsum("pij,pj,pkj->pik", vectors, values, vectors)


@dataclass(frozen=True, eq=False)
class PatchFlows:
    """Result of :func:`patch_flows`.

    Attributes
    ----------
    centres : ndarray (P, 2)
        Mean pixel of each patch's events.
    flows : ndarray (P, 2)
        [px/s].
    counts : ndarray (P,)
    information : ndarray (P, 2, 2)
        :func:`flow_information` of each flow at the last blur [1/px^2 of displacement over the window].
    solves : tuple of SolveResult
        One per blur level.
    """

    centres: np.ndarray
    flows: np.ndarray
    counts: np.ndarray
    information: np.ndarray
    solves: tuple[SolveResult, ...] = ()


def patch_flows(w, settings: PatchFlowSettings = PatchFlowSettings(), solver: Solver | None = None) -> PatchFlows:
    """Constant flow [px/s] of each patch with enough events, and how well it is determined.

    Each patch's flow maximises the normalised variance of its own IWE (all patches in one separable
    solve), once per blur of ``settings.sigmas``, each from the last: a wide blur first (a wide basin:
    from a zero start the sharp objective stops at a wrong local peak for large flows). Every level
    but the last uses every ``settings.coarse_step``-th event.

    Parameters
    ----------
    w : cmax.fitting.window.Window
    settings : PatchFlowSettings
        Patch grid, event counts, margin, blurs and iterations.
    solver : Solver, optional
        The backend (:func:`cmax.fitting.solvers.solve`); scipy's L-BFGS-B by default.
    """
    solver = ScipySolver() if solver is None else solver
    patches = make_patches(w, grid=settings.grid, min_events=settings.min_events, max_events=settings.max_events,
                           margin=settings.margin, min_margin_px=settings.min_margin_px)
    if patches is None:
        return PatchFlows(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2, 2)))
    sigmas = settings.sigmas
    q = np.zeros(2 * patches.count)
    bound = float(patches.margin)
    solves = []
    for stage, sigma in enumerate(sigmas):
        subset = patches.every(settings.coarse_step if stage < len(sigmas) - 1 else 1)
        loss = _flow_loss(subset, w.settings.sigma if sigma is None else sigma, w.T)
        result = solve(GradientLoss(loss.fun_and_grad), q, np.full(q.size, -bound), np.full(q.size, bound), solver,
                       iterations=settings.iterations, tolerances=settings.tolerances)
        solves.append(result)
        q = result.x
    q = q.reshape(patches.count, 2)
    information = flow_information(loss.fun_and_grad, q, settings.information_step_px,
                                   settings.information_floor)
    return PatchFlows(patches.centres, q / w.T, patches.counts, information, tuple(solves))


def _field_matrices(centres: np.ndarray, K: np.ndarray, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """``A`` (P, 2, 3) and ``B`` (P, 2, 3) of the motion field at pixel centres, from the se3 warp."""
    Kt = torch.as_tensor(K, dtype=torch.float64)
    rays = torch.from_numpy(np.column_stack([centres, np.ones(len(centres))]) @ np.linalg.inv(K).T)
    d = torch.full((len(centres),), dt, dtype=torch.float64)
    x0, y0 = torch.from_numpy(centres[:, 0]), torch.from_numpy(centres[:, 1])
    A, B = np.zeros((len(centres), 2, 3)), np.zeros((len(centres), 2, 3))
    for j in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[j] = 1.0
        for target, v, om in ((A, e, e * 0), (B, e * 0, e)):
            x, y = warp_se3(rays, d, v, om, torch.ones(len(centres), dtype=torch.float64), Kt)
            target[:, 0, j] = ((x0 - x) / dt).numpy()  # u = (x_i - x_ref) / dt
            target[:, 1, j] = ((y0 - y) / dt).numpy()
    return A, B


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors (count, 3)."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r = np.sqrt(1 - z * z)
    phi = i * math.pi * (3 - math.sqrt(5))
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _row_transforms(weights: np.ndarray) -> np.ndarray:
    """Square roots (P, 2, 2) of per-patch weights: counts (P,) or information matrices (P, 2, 2).

    Normalised so that the median patch has unit weight.
    """
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim == 1:
        return np.sqrt(weights / np.median(weights))[:, None, None] * np.eye(2)
    values, vectors = np.linalg.eigh(0.5 * (weights + weights.transpose(0, 2, 1)))
    roots = np.sqrt(np.clip(values, 0, None))
    return np.einsum("pij,pj,pkj->pik", vectors, roots / max(float(np.median(roots)), 1e-12), vectors)


def _weighted_system(centres: np.ndarray, flows: np.ndarray, weights: np.ndarray, K: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Motion-field rows ``L A``, ``L B`` (P, 2, 3) and flows ``L u`` (2P,), each patch's rows times ``L``,
    the square root of its weight (:func:`_row_transforms`)."""
    A, B = _field_matrices(centres, K)
    L = _row_transforms(weights)                                           # (P, 2, 2)
    LA, LB = np.einsum("pij,pjk->pik", L, A), np.einsum("pij,pjk->pik", L, B)
    return LA, LB, np.einsum("pij,pj->pi", L, flows).reshape(2 * len(centres))


def motion_from_flows(centres: np.ndarray, flows: np.ndarray, weights: np.ndarray, K: np.ndarray, speed: float,
                      *, directions: int = 3000, refine: bool = True, omega: np.ndarray | None = None,
                      cap_directions: int = 400, cap_radius: float = 1.5, negative_depth_penalty: float = 4.0,
                      min_patches: int = 4) -> tuple[np.ndarray, np.ndarray, float]:
    """Best ``v`` (3,) [m/s, norm ``speed``], ``omega`` (3,) [rad/s] and the weighted RMS residual [px/s].

    Parameters
    ----------
    centres : ndarray (P, 2)
        Pixels of the flows.
    flows : ndarray (P, 2)
        [px/s].
    weights : ndarray (P,) or (P, 2, 2)
        Per-patch weights: event counts, or the information matrices of
        :func:`flow_information` (the residual ``r`` of a patch costs ``r^T I r``:
        a flow along an edge counts for nothing).
    K : ndarray (3, 3)
    speed : float
        ``|v|`` [m/s].
    directions : int
        Candidate directions (Fibonacci sphere; 3000: ~3.7 deg apart).
    refine : bool
        Then ``cap_directions`` directions in a cap of ``cap_radius`` spacings around the best.
    omega : ndarray (3,), optional
        A known angular velocity [rad/s] (a gyroscope's): it is held, and each
        direction's least squares solves the patches' inverse depths only.
    negative_depth_penalty : float
        A direction's residual is multiplied by ``1 + negative_depth_penalty * x``, ``x`` the fraction of
        negative inverse depths.
    min_patches : int
        Fewer flows raise a ValueError.
    """
    P = len(centres)
    if P < max(3, min_patches):
        raise ValueError(f"need at least {max(3, min_patches)} patches with events to initialise the motion, got {P}")
    LA, LB, b = _weighted_system(centres, flows, weights, K)
    known = None if omega is None else np.asarray(omega, dtype=np.float64).reshape(3)
    t = fibonacci_sphere(directions)                                       # (D, 3)
    score, omegas, residual = _direction_scores(t, LA, LB, b, speed, known, negative_depth_penalty)
    best = int(np.argmin(score))
    if refine and cap_directions > 0:  # a finer cap around the best: the sphere's points are ~3.7 deg apart for 3000
        spacing = math.sqrt(4 * math.pi / directions)
        t = np.vstack([t[best], spherical_cap(t[best], cap_radius * spacing, cap_directions)])
        score, omegas, residual = _direction_scores(t, LA, LB, b, speed, known, negative_depth_penalty)
        best = int(np.argmin(score))
    return speed * t[best], omegas[best], float(residual[best])


def spherical_cap(axis: np.ndarray, radius: float, count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors (count, 3) within ``radius`` [rad] of the unit vector ``axis``."""
    i = np.arange(count) + 0.5
    cos_t = 1 - (1 - math.cos(radius)) * i / count                         # uniform in area
    sin_t = np.sqrt(1 - cos_t ** 2)
    phi = i * math.pi * (3 - math.sqrt(5))
    helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    return (cos_t[:, None] * axis + sin_t[:, None] * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))


def _direction_scores(t: np.ndarray, LA: np.ndarray, LB: np.ndarray, b: np.ndarray, speed: float,
                      omega: np.ndarray | None = None, negative_depth_penalty: float = 4.0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Score (D,), omega (D, 3) [rad/s] and RMS residual (D,) of directions ``t`` (D, 3).

    The weighted motion-field rows ``LA``, ``LB`` (P, 2, 3) and flows ``b`` (2P,);
    per direction one least-squares problem in ``omega`` (unless it is known)
    and the patches' inverse depths. The score is the residual times
    ``1 + negative_depth_penalty * x`` (x: the fraction of negative depths).
    """
    x, residual = _solve_directions(t, LA, LB, b, speed, omega)
    negative = (x[:, 3:] < 0).mean(1)
    return residual * (1 + negative_depth_penalty * negative), x[:, :3], residual


def _solve_directions(t: np.ndarray, LA: np.ndarray, LB: np.ndarray, b: np.ndarray, speed: float,
                      omega: np.ndarray | None = None, ridge: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares ``(omega, rho_1..P)`` (D, 3 + P) and RMS residual (D,) for each direction of ``t`` (D, 3).

    Patch ``p``'s two rows are ``b_p ~ LB_p omega + a_p rho_p`` with ``a_p = speed LA_p t``: its inverse
    depth enters no other row, so it is eliminated in closed form (the Schur complement of the
    block-diagonal depth part) and each direction solves one 3x3 system for ``omega``, then
    ``rho_p = a_p . (b_p - LB_p omega) / (|a_p|^2 + ridge)``: the solution of the dense normal
    equations with ``ridge`` added to their diagonal, in O(D P) instead of O(D P^3).
    With a known ``omega`` (3,) [rad/s] its flow is taken off ``b`` and only the inverse depths are
    solved; the returned ``omega`` columns are that one.
    """
    P, D = LA.shape[0], len(t)
    b = np.asarray(b, dtype=np.float64).reshape(P, 2)
    rows_A, rows_B = LA.reshape(2 * P, 3), LB.reshape(2 * P, 3)
    a = (speed * t @ rows_A.T).reshape(D, P, 2)                            # rho_p multiplies it (batched matmuls:
    norm = np.einsum("dpi,dpi->dp", a, a) + ridge                         # einsum is 10x slower on these shapes)
    if omega is None:
        cross = np.einsum("pik,pij->pkj", LB, LA).reshape(3 * P, 3)       # LB_p^T LA_p
        Ba = (speed * t @ cross.T).reshape(D, P, 3)                        # (D, P, 3): LB_p^T a_p
        ab = np.einsum("dpi,pi->dp", a, b)                                 # (D, P): a_p . b_p
        schur = rows_B.T @ rows_B + ridge * np.eye(3) - (Ba / norm[..., None]).transpose(0, 2, 1) @ Ba
        rhs = rows_B.T @ b.reshape(2 * P) - np.einsum("dpk,dp->dk", Ba, ab / norm)
        omegas = np.linalg.solve(schur, rhs[..., None])[..., 0]           # (D, 3)
    else:
        omegas = np.broadcast_to(np.asarray(omega, dtype=np.float64), (D, 3))
    rest = b[None] - (omegas @ rows_B.T).reshape(D, P, 2)                  # b_p - LB_p omega
    rho = np.einsum("dpi,dpi->dp", a, rest) / norm                         # (D, P)
    residual = np.sqrt(np.mean((rest - a * rho[..., None]) ** 2, axis=(1, 2)))
    return np.concatenate([omegas, rho], axis=1), residual


def explain_flows(centres: np.ndarray, flows: np.ndarray, weights: np.ndarray, K: np.ndarray,
                  directions: np.ndarray, speed: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How well given translation directions explain the patch flows.

    For each direction (D, 3) the rotation and the patches' inverse depths
    are solved by weighted least squares, as in :func:`motion_from_flows`.

    Returns
    -------
    residual : ndarray (D,)
        Weighted RMS residual [px/s].
    omega : ndarray (D, 3)
        [rad/s].
    inverse_depth : ndarray (D, P)
        Per patch [1/m] for ``|v| = speed`` m/s.
    """
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    x, residual = _solve_directions(directions, *_weighted_system(centres, flows, weights, K), speed)
    return residual, x[:, :3], x[:, 3:]
