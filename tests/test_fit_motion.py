"""The se3 motion of ``cmax.fit`` with a known speed: patch flows, their information, the motion-field fit,
and the local refinement (``cmax.fitting.patch_flow``, ``cmax.fitting.motion``).

Ground truth comes from scenes built here: 3D points (a far wall and nearer boxes) whose events are
projections at their own times under a constant twist, so the motion field is exact.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from cmax.events import Events
from cmax.fitting import FitSettings, PatchFlowSettings, RefineSettings, fit
from cmax.fitting.motion import LocalMotionObjective, refine_motion_local, strided_argmax, sweep_stride
from cmax.fitting.patch_flow import (
    _field_matrices, _solve_directions, _weighted_system, fibonacci_sphere, flow_information, make_patches, motion_from_flows, patch_flows, spherical_cap,
)
from cmax.fitting.solvers import ScipySolver
from cmax.fitting.window import Window
from cmax.geometry import se3_exp


@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread, as ``cmax.fit`` runs (sums in another order move the flows' optimiser a little)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


K346 = np.array([[226.0, 0, 173.0], [0, 226.0, 130.0], [0, 0, 1]])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))


def point_scene(seed: int, *, width: int = 346, height: int = 260, duration_s: float = 0.1665,
                points: int = 6000, events_per_point: int = 8, max_omega_deg: float = 12.0):
    """Events of random 3D points (a wall at 5-6 m, four boxes at 1.2-3.5 m) under a constant twist.

    The speed is 0.4-0.8 m/s, each axis of ``omega`` uniform within ``max_omega_deg`` [deg/s].

    Returns events, K (3, 3), v (3,) [m/s], omega (3,) [rad/s]; the depths belong to the window's middle.
    """
    rng = np.random.default_rng(seed)
    K = K346 * [[width / 346], [height / 260], [1]]
    v = rng.normal(size=3)
    v *= rng.uniform(0.4, 0.8) / np.linalg.norm(v)
    omega = np.radians(rng.uniform(-max_omega_deg, max_omega_deg, 3))
    pixels = np.column_stack([rng.uniform(-20, width + 20, points), rng.uniform(-20, height + 20, points)])
    z = rng.uniform(5.0, 6.0, points)
    for _ in range(4):
        x0, y0 = rng.uniform(0, width - 80), rng.uniform(0, height - 60)
        inside = ((pixels[:, 0] > x0) & (pixels[:, 0] < x0 + rng.uniform(60, 140))
                  & (pixels[:, 1] > y0) & (pixels[:, 1] < y0 + rng.uniform(50, 110)))
        z[inside] = rng.uniform(1.2, 3.5)
    X = np.column_stack([(pixels - K[:2, 2]) / K[0, 0] * z[:, None], z])        # camera at the middle
    t = np.sort(rng.uniform(0, duration_s, points * events_per_point))
    which = rng.integers(0, points, len(t))
    xs, ys = np.full(len(t), -1.0), np.full(len(t), -1.0)
    bins = np.linspace(0, duration_s, 300)
    for lo, hi in zip(bins[:-1], bins[1:]):                                       # one pose per 0.6 ms
        sel = (t >= lo) & (t < hi)
        T_mid_c = se3_exp(np.r_[v, omega] * (0.5 * (lo + hi) - duration_s / 2))  # camera at t in the middle's frame
        Xc = (X[which[sel]] - T_mid_c[:3, 3]) @ T_mid_c[:3, :3]
        xs[sel] = K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2]
        ys[sel] = K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]
    keep = (xs >= 0) & (xs < width - 0.5) & (ys >= 0) & (ys < height - 0.5)
    events = Events(np.round(xs[keep]).astype(np.uint16), np.round(ys[keep]).astype(np.uint16),
                    np.round(t[keep] * 1e6).astype(np.int64), np.ones(int(keep.sum()), np.int8), width, height)
    return events, K, v, omega


def make_window(events: Events, K: np.ndarray) -> Window:
    return Window.from_events(events, K, FitSettings(contrast="variance", polarity_split=False))


def flows_of(w: Window, **settings) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """centres, flows, counts, information of :func:`patch_flows` with these :class:`PatchFlowSettings`."""
    r = patch_flows(w, PatchFlowSettings(**settings), ScipySolver())
    return r.centres, r.flows, r.counts, r.information


def refine(w: Window, v, omega, speed, **options) -> tuple[np.ndarray, np.ndarray]:
    outcome = refine_motion_local(w, v, omega, speed, RefineSettings(), ScipySolver(), **options)
    return outcome.v, outcome.omega


def moving_pattern(flow_px, *, lines: bool = False, width: int = 200, height: int = 160, seed: int = 0) -> Events:
    """Random dots (10 events each), or vertical lines 8 px apart (one event per random point), moving by
    ``flow_px`` (2,) [px] over 0.1 s."""
    rng = np.random.default_rng(seed)
    n = 15000 if lines else 1500
    p = np.column_stack([rng.uniform(-30, width + 30, n), rng.uniform(-30, height + 30, n)])
    if lines:
        p[:, 0] = np.round(p[:, 0] / 8) * 8
    t = np.sort(rng.uniform(0, 0.1, n if lines else 10 * n))
    xy = p[rng.integers(0, n, len(t))] + np.asarray(flow_px, float) * (t[:, None] / 0.1 - 0.5)
    k = (xy[:, 0] >= 0) & (xy[:, 0] <= width - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= height - 1)
    return Events(np.round(xy[k, 0]).astype(np.uint16), np.round(xy[k, 1]).astype(np.uint16),
                  np.round(t[k] * 1e6).astype(np.int64), np.ones(int(k.sum()), np.int8), width, height)


# ----------------------------------------------------------------------------------------------------
# Patch flows and their information
# ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flow_px", [(6.0, -3.0), (-18.0, 4.0)])
def test_patch_flows_recover_a_constant_flow(flow_px):
    K = np.array([[150.0, 0, 100], [0, 150.0, 80], [0, 0, 1]])
    w = make_window(moving_pattern(flow_px), K)
    centres, flows, counts, information = flows_of(w, grid=(2, 3))
    assert centres.shape == (6, 2) and flows.shape == (6, 2) and counts.shape == (6,)
    assert information.shape == (6, 2, 2)
    np.testing.assert_allclose(flows * w.T, np.broadcast_to(flow_px, (6, 2)), atol=0.35)
    assert np.all(np.linalg.eigvalsh(information) > 0)


def test_flow_information_is_small_along_edges():
    """Vertical lines: the flow across them (x) is sharp, along them (y) nearly free (the aperture problem)."""
    K = np.array([[150.0, 0, 100], [0, 150.0, 80], [0, 0, 1]])
    w = make_window(moving_pattern((6.0, -3.0), lines=True), K)
    _, flows, _, information = flows_of(w, grid=(2, 3))
    np.testing.assert_allclose(flows[:, 0] * w.T, 6.0, atol=0.35)
    assert np.all(information[:, 0, 0] > 4 * information[:, 1, 1])  # 5-10x measured; dots: within 3x
    dots = make_window(moving_pattern((6.0, -3.0)), K)
    info_dots = flows_of(dots, grid=(2, 3))[3]
    ratio = info_dots[:, 0, 0] / info_dots[:, 1, 1]
    assert np.all((ratio > 0.3) & (ratio < 3))


def test_flow_information_of_a_quadratic_is_its_curvature():
    curvature = np.array([[4.0, 1.0], [1.0, 2.0]])

    def fun_and_grad(p):  # minus a contrast peaked at q = 1 with curvature C
        d = p.reshape(3, 2) - 1.0
        return 0.5 * float(np.einsum("pi,ij,pj->", d, curvature, d)), (d @ curvature).reshape(-1)

    information = flow_information(fun_and_grad, np.full((3, 2), 1.0))
    np.testing.assert_allclose(information, np.broadcast_to(curvature, (3, 2, 2)), atol=1e-9)


# ----------------------------------------------------------------------------------------------------
# The motion-field fit
# ----------------------------------------------------------------------------------------------------
def exact_patch_flows(rng: np.random.Generator, v: np.ndarray, omega: np.ndarray, patches: int = 20
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Random patch centres (P, 2) on a 346x260 sensor and their exact motion-field flows (P, 2) [px/s]
    for the twist ``(v, omega)`` and random inverse depths 0.2-1 1/m."""
    centres = np.column_stack([rng.uniform(20, 326, patches), rng.uniform(20, 240, patches)])
    rho = rng.uniform(0.2, 1.0, patches)
    A, B = _field_matrices(centres, K346)
    return centres, rho[:, None] * (A @ v) + B @ omega


def test_motion_field_fit_recovers_the_twist_from_exact_patch_flows():
    v, omega = np.array([0.2, -0.1, 0.5]), np.radians([5.0, -10.0, 3.0])
    centres, flows = exact_patch_flows(np.random.default_rng(1), v, omega)
    v_fit, omega_fit, residual = motion_from_flows(centres, flows, np.ones(20), K346, float(np.linalg.norm(v)),
                                                   directions=20000)
    assert angle_deg(v_fit, v) < 2.0
    np.testing.assert_allclose(omega_fit, omega, atol=np.radians(0.5))


def test_a_known_rotation_is_held_and_only_the_direction_is_solved():
    """With the gyro's omega the exact flows leave almost no residual at the best direction (the
    sphere's spacing is all that is left), and a rotation 3 deg/s off on one axis leaves 10x more."""
    v, omega = np.array([0.2, -0.1, 0.5]), np.radians([5.0, -10.0, 3.0])
    centres, flows = exact_patch_flows(np.random.default_rng(1), v, omega)
    speed = float(np.linalg.norm(v))
    v_fit, omega_fit, residual = motion_from_flows(centres, flows, np.ones(20), K346, speed, omega=omega,
                                                   directions=20000)
    assert angle_deg(v_fit, v) < 1.0
    np.testing.assert_array_equal(omega_fit, omega)
    assert residual < 0.01 * np.abs(flows).mean()
    wrong = omega + np.radians([3.0, 0.0, 0.0])
    _, _, residual_wrong = motion_from_flows(centres, flows, np.ones(20), K346, speed, omega=wrong,
                                             directions=20000)
    assert residual_wrong > 10 * residual


@pytest.mark.parametrize("known_omega", [False, True])
def test_direction_solves_equal_a_dense_least_squares_per_direction(known_omega):
    """The closed-form elimination of each patch's inverse depth gives what ``np.linalg.lstsq`` gives on the
    full (2P, 3 + P) system of each direction (noisy flows, information weights, 50 directions)."""
    rng = np.random.default_rng(5)
    v, omega = np.array([0.2, -0.1, 0.5]), np.radians([5.0, -10.0, 3.0])
    centres, flows = exact_patch_flows(rng, v, omega)
    flows = flows + rng.normal(0, 5.0, flows.shape)
    information = np.einsum("pij,pkj->pik", *(2 * [rng.normal(size=(20, 2, 2))])) + 0.1 * np.eye(2)
    LA, LB, b = _weighted_system(centres, flows, information, K346)
    t, speed = fibonacci_sphere(50), 0.7
    known = omega if known_omega else None
    x, residual = _solve_directions(t, LA, LB, b, speed, known)
    for d in range(len(t)):
        field = (speed * LA @ t[d]).reshape(40)                  # rho_p's column has patch p's two rows
        columns = np.zeros((40, 20))
        columns[np.arange(40), np.arange(40) // 2] = field
        if known_omega:
            solution, *_ = np.linalg.lstsq(columns, b - LB.reshape(40, 3) @ omega, rcond=None)
            solution = np.r_[omega, solution]
        else:
            solution, *_ = np.linalg.lstsq(np.column_stack([LB.reshape(40, 3), columns]), b, rcond=None)
        np.testing.assert_allclose(x[d], solution, rtol=1e-7, atol=1e-9 * np.abs(solution).max())
        rms = np.sqrt(np.mean((np.column_stack([LB.reshape(40, 3), columns]) @ solution - b) ** 2))
        assert residual[d] == pytest.approx(rms, rel=1e-7)


def test_information_weights_ignore_flows_along_edges():
    """Eight of 20 patches see one edge each: their flow along the edge is garbage (+-40 px/s) and their
    information rank one. Weighted by information the twist comes back; weighted by counts it does not."""
    rng = np.random.default_rng(3)
    v, omega = np.array([0.3, -0.1, 0.4]), np.radians([5.0, -10.0, 3.0])
    centres, flows = exact_patch_flows(rng, v, omega)
    information = np.broadcast_to(np.eye(2), (20, 2, 2)).copy()
    for p in range(8):
        along = np.array([np.cos(p), np.sin(p)])
        normal = np.array([-along[1], along[0]])
        flows[p] += rng.choice([-40.0, 40.0]) * along
        information[p] = np.outer(normal, normal) + 1e-4 * np.eye(2)
    speed = float(np.linalg.norm(v))
    v_info, omega_info, _ = motion_from_flows(centres, flows, information, K346, speed)
    v_count, _, _ = motion_from_flows(centres, flows, np.ones(20), K346, speed)
    assert angle_deg(v_info, v) < 2.0
    np.testing.assert_allclose(omega_info, omega, atol=np.radians(0.3))
    assert angle_deg(v_count, v) > 5.0


def test_patch_motion_survives_fast_rotations():
    """Rotations up to 40 deg/s move patches by ~25 px over the window. These windows are chaotic: a
    relative change of 1e-7 in the blurred images (float rounding: torch against the compiled patch
    images, one torch thread against two) moves single seeds between 2 and 50 deg, so only statistics
    over seeds 1-12 are asserted. The single-stage, count-weighted initialiser of before (margin 0.25 of a
    patch, sharp blur from a zero start) loses the motion (median 57-60 deg over the paths tried); two
    blurs, a wider margin and information weights keep it on most seeds (median 10-18 deg, better than
    before on 7-10 of 12, worst-axis omega error median 2.2-3.5 deg/s; with the patch flows' ftol 1e-7 of
    2026-12-02: 10.2 deg, 7 of 12, 2.3 deg/s, one seed flipped from 17 to 114 deg), not on every one: on the
    failing seeds the refinement that follows starts from a wrong direction."""
    new, old, omega_errors = [], [], []
    for seed in range(1, 13):
        events, K, v, omega = point_scene(seed, max_omega_deg=40)
        w = make_window(events, K)
        speed = float(np.linalg.norm(v))
        centres, flows, counts, information = flows_of(w)
        v_new, omega_new, _ = motion_from_flows(centres, flows, information, K, speed)
        new.append(angle_deg(v_new, v))
        omega_errors.append(np.degrees(np.abs(omega_new - omega)).max())
        centres, flows, counts, _ = flows_of(w, margin=0.25, sigmas=(None,))
        v_old, _, _ = motion_from_flows(centres, flows, counts, K, speed, refine=False)
        old.append(angle_deg(v_old, v))
    assert np.median(new) < 0.5 * np.median(old) and np.median(old) > 30.0
    assert sum(a < b for a, b in zip(new, old)) >= 7
    assert np.median(omega_errors) < 4.0                              # deg/s, worst axis


def test_the_fine_cap_beats_the_sphere_spacing():
    rng = np.random.default_rng(5)
    centres = np.column_stack([rng.uniform(20, 326, 20), rng.uniform(20, 240, 20)])
    rho = rng.uniform(0.2, 1.0, 20)
    v, omega = np.array([0.21, 0.33, -0.42]), np.radians([-4.0, 6.0, 2.0])
    A, B = _field_matrices(centres, K346)
    flows = rho[:, None] * (A @ v) + B @ omega
    speed = float(np.linalg.norm(v))
    coarse = motion_from_flows(centres, flows, np.ones(20), K346, speed, directions=300, refine=False)[0]
    fine = motion_from_flows(centres, flows, np.ones(20), K346, speed, directions=300, refine=True)[0]
    assert angle_deg(fine, v) < angle_deg(coarse, v)
    assert angle_deg(fine, v) < 2.5  # 300 directions are ~11.7 deg apart; the cap's 400 ~1.5 deg


def test_spherical_cap():
    axis = np.array([1.0, 2.0, -2.0]) / 3
    cap = spherical_cap(axis, 0.1, 200)
    assert cap.shape == (200, 3)
    np.testing.assert_allclose(np.linalg.norm(cap, axis=1), 1.0)
    angles = np.arccos(np.clip(cap @ axis, -1, 1))
    assert angles.max() <= 0.1 + 1e-9 and angles.min() < 0.01


def test_motion_from_flows_rejects_too_few_patches():
    with pytest.raises(ValueError, match="at least 4 patches"):
        motion_from_flows(np.zeros((3, 2)), np.zeros((3, 2)), np.ones(3), K346, 1.0)


# ----------------------------------------------------------------------------------------------------
# The local refinement and the whole fit
# ----------------------------------------------------------------------------------------------------
def _patch_objective(seed: int):
    """The refinement's objective on a point scene's window, its true ``v`` and ``omega``, and 24 inverse-depth
    candidates [1/m]."""
    events, K, v, omega = point_scene(seed)
    w = make_window(events, K)
    patches = make_patches(w, grid=(6, 8), min_events=100, max_events=20_000, margin=0.3)
    objective = LocalMotionObjective.build(w, patches, float(np.linalg.norm(v)))
    return objective, v, omega, np.exp(np.linspace(np.log(1 / 60), np.log(2.0), 24))


def test_local_objective_peaks_at_the_true_motion():
    objective, v, omega, candidates = _patch_objective(1)

    def score(v_, omega_):
        rho = objective.sweep_rho(v_, omega_, candidates)
        with torch.no_grad():
            return float(objective.values(torch.from_numpy(objective.params(v_, omega_, rho))).sum())

    tilted = se3_exp(np.r_[0, 0, 0, 0.25, 0, 0])[:3, :3] @ v                       # 14 deg off
    assert score(v, omega) > score(tilted, omega)
    assert score(v, omega) > score(v, omega + np.radians([3.0, 0, 0]))


def test_depth_sweep_of_the_patches_equals_one_warp_per_candidate():
    """``sweep_rho`` warps once and projects per candidate (``PatchMotionContrast.at_depths``): each row
    equals the full objective at that depth, and the chosen depths are the per-candidate argmax."""
    objective, v, omega, candidates = _patch_objective(1)
    patches = objective.patches
    v_, omega_ = v * 1.0, omega + np.radians([2.0, -1.0, 0.5])
    with torch.no_grad():
        loop = np.stack([objective.values(torch.from_numpy(objective.params(v_, omega_, np.full(patches.count, c))))
                         .double().numpy() for c in candidates])                       # (C, P)
        dtype = objective.rays.dtype
        rows = torch.as_tensor(candidates, dtype=dtype)[:, None].expand(-1, len(objective.rays))
        batched = objective.contrast.at_depths(torch.as_tensor(v_, dtype=dtype), torch.as_tensor(omega_, dtype=dtype),
                                               rows).double().numpy()
    np.testing.assert_allclose(batched, loop, rtol=1e-5)
    clear = np.sort(loop, 0)[-1] - np.sort(loop, 0)[-2] > 1e-4 * np.abs(loop).max()   # no near-tie at the top
    assert clear.sum() >= patches.count // 2
    np.testing.assert_array_equal(objective.sweep_rho(v_, omega_, candidates)[clear], candidates[loop.argmax(0)][clear])


def _counted(table: np.ndarray):
    """``values(index)`` over ``table`` (count, columns) for :func:`strided_argmax`, and the rows it scored."""
    scored = []

    def values(index: np.ndarray) -> np.ndarray:
        scored.append(index.shape[0])
        return np.take_along_axis(table, index, 0)
    return values, scored


@pytest.mark.parametrize("count, stride", [(24, 3), (24, 4), (25, 3), (7, 2), (5, 8), (24, 1)])
def test_strided_argmax_finds_every_single_peak(count, stride):
    """On columns that rise strictly to one peak and fall strictly after it, the strided search returns the
    full argmax, scoring about ``count / stride + 2 (stride - 1)`` rows."""
    rng = np.random.default_rng(count * 10 + stride)
    columns = 400
    peak = rng.integers(0, count, columns)
    steps = rng.choice([0.25, 0.5, 1.0, 3.0], (count, columns))
    rows = np.arange(count)[:, None]
    rise = np.cumsum(np.where(rows <= peak, steps, 0.0), 0)
    fall = np.cumsum(np.where(rows > peak, steps, 0.0), 0)
    table = rise - fall
    values, scored = _counted(table)
    np.testing.assert_array_equal(strided_argmax(values, count, columns, stride), table.argmax(0))
    expected = count if stride == 1 else len(set(range(0, count, stride)) | {count - 1}) + 2 * (stride - 1)
    assert sum(scored) == expected


def test_strided_argmax_can_miss_a_narrow_second_peak():
    """Its limit: a peak narrower than the stride between two coarse rows is not seen."""
    table = np.array([[5.0, 4.0, 3.0, 2.0, 9.0, 2.0, 1.0]]).T      # the best (row 4) sits between rows 3 and 6
    values, _ = _counted(table)
    assert strided_argmax(values, 7, 1, 3).tolist() == [0]
    assert strided_argmax(values, 7, 1, 1).tolist() == [4]


def test_strided_depth_sweep_equals_the_full_sweep_on_the_refinement_patches():
    """Every third candidate, then the two on each side of each patch's best, picks each patch's depth as
    scoring every candidate does on the refinement's patches (their contrast over inverse depth has one peak)."""
    objective, v, omega, candidates = _patch_objective(1)
    for v_, omega_ in [(v, omega), (v, omega + np.radians([2.0, -1.0, 0.5])),
                       (se3_exp(np.r_[0, 0, 0, 0.0, 0.2, 0.1])[:3, :3] @ v, omega)]:
        np.testing.assert_array_equal(objective.sweep_rho(v_, omega_, candidates, 3),
                                      objective.sweep_rho(v_, omega_, candidates, 1))


@pytest.mark.parametrize("depth_range, stride", [((1.0, 6.5), 3), ((0.5, 60.0), 1), ((2.0, 2.5), 3), ((1.0, 1.0), 1)])
def test_the_sweep_stride_keeps_the_coarse_candidates_within_the_coarse_step(depth_range, stride):
    """The stride is the number of candidate steps (log-uniform in inverse depth) within ``rho_coarse_step``,
    capped where a wider stride would score more candidates than it saves (24 candidates: 3, 13 scored)."""
    settings = RefineSettings()
    assert sweep_stride(settings, depth_range) == stride
    near, far = depth_range
    if far > near:
        spacing = np.log(far / near) / (settings.rho_candidates - 1)
        assert stride * spacing <= settings.rho_coarse_step + 1e-9
    assert sweep_stride(RefineSettings(rho_coarse_step=0.0), depth_range) == 1
    with pytest.raises(ValueError, match="rho_coarse_step"):
        RefineSettings(rho_coarse_step=-0.1)


def test_local_refinement_recovers_from_a_tilted_start():
    events, K, v, omega = point_scene(2)
    w = make_window(events, K)
    speed = float(np.linalg.norm(v))
    start = se3_exp(np.r_[0, 0, 0, 0.0, 0.2, 0.1])[:3, :3] @ v                     # 13 deg off
    v1, omega1 = refine(w, start, omega + np.radians([1.5, -1.5, 0]), speed)
    assert angle_deg(v1, v) < 4.0 < angle_deg(start, v)
    np.testing.assert_allclose(np.linalg.norm(v1), speed)
    np.testing.assert_allclose(omega1, omega, atol=np.radians(1.0))


@pytest.mark.parametrize("good_first", [True, False])
def test_refinement_keeps_the_best_of_several_starts(good_first):
    """A start on the far side (a direction 90 deg off with a wrong rotation) next to a good one: the
    better-scoring refinement wins, whichever order they come in."""
    events, K, v, omega = point_scene(2)
    w = make_window(events, K)
    speed = float(np.linalg.norm(v))
    bad = (np.cross(v, [0.0, 0.0, 1.0]) * speed / np.linalg.norm(np.cross(v, [0.0, 0.0, 1.0])),
           omega + np.radians([20.0, -20.0, 10.0]))
    good = (v, omega)
    first, second = (good, bad) if good_first else (bad, good)
    alone = refine(w, *bad, speed)
    outcome = refine_motion_local(w, *first, speed, RefineSettings(), ScipySolver(), more_starts=[second])
    assert angle_deg(outcome.v, v) < 4.0 < angle_deg(alone[0], v)
    # the winner is the solve whose end is returned (the stage judges that one)
    assert outcome.winner == (0 if good_first else 1)
    assert outcome.objective_after == min(r.fun for r in outcome.solves) == outcome.solves[outcome.winner].fun


@pytest.mark.parametrize("seed, max_omega_deg", [(1, 12.0), (2, 40.0)])
def test_fit_with_a_known_speed_recovers_the_motion_of_a_point_scene(seed, max_omega_deg):
    events, K, v, omega = point_scene(seed, max_omega_deg=max_omega_deg)
    r = fit(events, K, speed=float(np.linalg.norm(v)))
    assert angle_deg(r.v, v) < 4.0
    assert np.degrees(np.sqrt(np.mean((r.omega - omega) ** 2))) < 1.0
    np.testing.assert_allclose(np.linalg.norm(r.v), np.linalg.norm(v))


@pytest.mark.parametrize("motion_init", ["patches", "starts"])
def test_fit_with_a_known_rotation_holds_it_and_finds_the_direction(motion_init):
    """``fit(..., omega=...)``: the gyro's rotation comes back bit for bit, through either initialiser."""
    events, K, v, omega = point_scene(2, max_omega_deg=40.0)
    r = fit(events, K, speed=float(np.linalg.norm(v)), omega=omega, motion_init=motion_init)
    np.testing.assert_array_equal(r.omega, omega)
    assert angle_deg(r.v, v) < 4.0
    assert r.scale_known
