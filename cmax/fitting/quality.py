"""The quality verdict of a fitted window: ok, ambiguous, low parallax or failed.

A se3 fit picks one motion; contrast maximization has well-known near-ties that a wrong pick cannot
see from the inside: the mirrored translation ``v -> -v``, the rotation of the other sign
``omega -> -omega``, and the bas-relief trade, where the rotation takes over the translation's flow so
that ``-v`` explains the events nearly as well (Adelson & Bergen's bas-relief ambiguity; in event
data e.g. Gallego et al., CVPR 2018, Fig. 6). :func:`assess` scores each alternative on the fit's own
final motion objective, the patch-wise contrast of :class:`cmax.fitting.motion.LocalMotionObjective`,
with each motion's patch depths re-optimised by the same per-patch inverse-depth sweep the refinement
starts from (:meth:`~cmax.fitting.motion.LocalMotionObjective.sweep_rho`). An alternative within
*noise* of the fit makes the window ambiguous:

    gain_p = c_p(fit) - c_p(alternative)          (normalised contrast of patch p, each with its sweep)
    G      = sum_p gain_p                          (> 0: the fit is better)
    noise  = max(noise_sigmas * sqrt(P) * std_p(gain_p),  margin * sum_p (c_p(fit) - 1))
    ambiguous when G <= noise

The first term is the standard error of the summed gain over the ``P`` patches (a preference that only
some patches share is not evidence); the second a relative margin on the fit's own gain over the
unwarped events. :func:`choose_from_neighbours` resolves an ambiguous window of a sequence from the
motion of its confident neighbours (:func:`cmax.fitting.fit_sequence`), and :func:`choose_from_run` a run of
ambiguous windows with none, from the evidence of its windows summed under one motion.

``flow`` and ``rotation`` have no alternative motion of the same score, but a window with too little
motion can be fitted to a confident wrong answer: a motion that raises the contrast through a few
regions of the image (texture, the window's edges) while the true motion, under a pixel, is within the
blur. :func:`motion_within_noise` splits the fitted multi-reference contrast gain over a grid of cells
(:func:`cmax.contrast.cells.contrast_by_cell`, exact: the shares sum to the gain) and applies the same
rule as the ambiguity test:

    gain_c = (C_c(fit) - C_c(unwarped)) / C(unwarped)      (cell c's share of the normalised contrast)
    G      = sum_c gain_c = objective_after - 1
    noise  = motion_noise_sigmas * sqrt(P) * std_c(gain_c)  (P: cells with events)
    within noise when G <= noise

A motion that sharpens the scene gains in most cells; a gain carried by a few cells is not evidence.

Every model, finally: a gain that does not come from aligning events in time. On events without motion
(sensor noise, flicker, a static scene) a large motion still raises the contrast, because it sweeps the
events off one side of the image and leaves an empty band (the image's border, not the scene, makes the
image of warped events uneven). :func:`shuffled_gain_test` warps the same events by the same motion with
their timestamps permuted among them, which keeps that border effect and destroys any alignment:

    G_shuffled = gain of the fitted motion on the time-shuffled events
    not measured when G_shuffled >= shuffle_fraction * G

On moving scenes the shuffled events are blurred (``G_shuffled < 0``); on noise ``G_shuffled`` is
nearly ``G``. This is a permutation test in the sense of Good, "Permutation, Parametric and Bootstrap
Tests of Hypotheses" (Springer, 2005): the null of "no relation between an event's time and its place".

A se3 fit, last, assumes one constant velocity over the window. Events come at a rate proportional to the
image's speed times its gradients, so a camera that stops or starts inside the window leaves most of the
window's events in one half of it: :func:`rate_change` is the ratio of the busier half's events to the
other's. Beyond ``max_rate_change`` the window's motion is not steady, no single motion explains its events,
and the fit's own score is no evidence for its direction: the verdict is ``ambiguous`` (``Quality.unsteady``),
and ``fit_sequence`` gives the window its neighbours' motion (:func:`cmax.fitting.sequence.smooth_from_neighbours`).
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, replace
from typing import NamedTuple, Sequence

import numpy as np
import torch

from cmax.contrast.cells import contrast_by_cell
from cmax.fitting.motion import LocalMotionObjective, refine_motion_local, sweep_stride
from cmax.fitting.patch_flow import make_patches
from cmax.fitting.settings import QualitySettings
from cmax.iwe import accumulate_bilinear, blur, polarity_images
from cmax.warp import warp_se3

__all__ = ["Verdict", "LowMotionCause", "LowMotion", "QualitySettings", "Alternative", "Quality", "MotionScorer",
           "assess", "motion_within_noise", "shuffled_gain_test", "NO_MOTION", "verdict_of",
           "choose_from_neighbours", "choose_from_run", "alternative_motions", "rate_change", "sparse_reason",
           "small_parallax_reason", "min_ok_parallax", "isolated_events", "neighbour_counts", "noise_share",
           "noise_reason", "turned_motions", "best_turned", "turned_reason", "valley_turned", "valley_reason",
           "density_pixels"]


#: How a ``low_parallax`` reason ends when the permutation test (:func:`shuffled_gain_test`) found no motion at
#: all, for a reader of the text; code reads :attr:`Quality.cause` (:attr:`LowMotionCause.NO_MOTION`).
NO_MOTION = "the motion is not measured"


class Verdict(str, enum.Enum):
    """The quality of one window's fit, worst first: ``failed`` (a stage failed, ``success`` False),
    ``low_parallax`` (se3: ``parallax_px`` under ``FitSettings.low_parallax_px``; flow/rotation:
    ``motion_px`` under ``low_motion_px``, or a motion within noise, :func:`motion_within_noise`; every
    model: a gain that time-shuffled events share, :func:`shuffled_gain_test`; se3 with a free rotation: a rotation
    alone explains the events, :func:`cmax.fitting.rotation_only.rotation_only_test`),
    ``ambiguous`` (se3: an alternative motion scores within noise, or the motion is not steady over the
    window, :func:`rate_change`), ``ok``."""

    OK = "ok"
    AMBIGUOUS = "ambiguous"
    LOW_PARALLAX = "low_parallax"
    FAILED = "failed"


class LowMotionCause(str, enum.Enum):
    """Which rule made a fit ``low_parallax`` (the order in which the fit tries them):

    * ``parallax``: se3 parallax under ``FitSettings.low_parallax_px``;
    * ``motion``: flow/rotation motion under ``FitSettings.low_motion_px``;
    * ``cell_noise``: a contrast gain within the noise of its spread over the image's cells
      (:func:`motion_within_noise`);
    * ``no_motion``: the time-shuffled events gain as much, or the fit gains nothing
      (:func:`shuffled_gain_test`): the events' times and places are unrelated (noise, flicker, a static
      scene), so a longer window is no cure;
    * ``rotation_only``: se3 with a free rotation: a rotation alone explains the events within noise
      (:func:`cmax.fitting.rotation_only.rotation_only_test`): the translation and the depth are not measured,
      whatever parallax the fit reports (a camera that only turns, or hovers).
    """

    PARALLAX = "parallax"
    MOTION = "motion"
    CELL_NOISE = "cell_noise"
    NO_MOTION = "no_motion"
    ROTATION_ONLY = "rotation_only"


@dataclass(frozen=True)
class LowMotion:
    """Why a fit moved the events too little to trust: the rule (``cause``) and a sentence (``reason``)."""

    cause: LowMotionCause
    reason: str


@dataclass(frozen=True, eq=False)
class Alternative:
    """One alternative motion of a window: ``name`` (``mirrored``, ``rotation_flipped``, ``bas_relief``),
    ``v`` (3,) [m/s] and ``omega`` (3,) [rad/s], the summed gain of the fit over it (> 0: the fit is
    better), its noise (see the module docstring) and whether the gain is within it."""

    name: str
    v: np.ndarray
    omega: np.ndarray
    gain: float
    noise: float
    within_noise: bool


@dataclass(frozen=True, eq=False)
class Quality:
    """The verdict of one window and why.

    Attributes
    ----------
    verdict : Verdict
    reason : str
    alternatives : tuple of Alternative
        The scored alternatives (empty when not tested).
    resolution : str
        ``fit_sequence``: how an ambiguous window was resolved from its neighbours, or why not ("" when
        not ambiguous or not in a sequence).
    resolved : bool
        Whether ``fit_sequence`` resolved it (kept the fit or took an alternative).
    replaced : (v, omega) or None
        The window's own fit ``(v (3,), omega (3,))`` when ``fit_sequence`` replaced it by an alternative, or when
        a rotation alone explains the window and scores at least as well (``cause`` ``rotation_only``:
        ``FitResult.omega`` is the rotation-only fit's).
    cause : LowMotionCause or None
        The rule behind a ``low_parallax`` verdict (None for the other verdicts).
    rate_change : float or None
        The window's :func:`rate_change` (se3 with a fitted motion; None when not measured).
    unsteady : bool
        ``rate_change`` is over ``QualitySettings.max_rate_change``: the motion is not steady over the window
        (ambiguous: no single motion explains its events; ``fit_sequence`` gives it its neighbours' motion).
    sparse : bool
        The window was fitted on fewer events per pixel than ``QualitySettings.min_event_density`` (per pixel of
        :func:`density_pixels`, :func:`sparse_reason`): ambiguous, since the ambiguity test cannot vouch for its
        direction.
    on_bound : bool
        At least ``QualitySettings.max_bound_share`` of the events' depth lies on one end of the depth range
        (:func:`bound_reason`): ambiguous, since the depth is clipped and the motion may be bent to keep the
        rest inside.
    small_parallax : bool
        se3 with a free rotation: ``parallax_px`` under ``QualitySettings.min_ok_parallax_px``, more on an image
        of fewer pixels than ``min_ok_parallax_area`` (:func:`small_parallax_reason`, :func:`min_ok_parallax`):
        ambiguous, since a rotation absorbs most of what a turn of so little translation changes in the image.
    noisy : bool
        More than ``QualitySettings.max_noise_share`` of the events are estimated to be background-activity noise
        (:func:`noise_reason`): ambiguous, since noise pixels enter the depth map and pull the depth sweep.
    noise_share : float or None
        The window's :func:`noise_share` (se3, with a given pose too; None when not measured).
    turned : bool
        se3 with a free rotation: a motion ``QualitySettings.bas_relief_turn_deg`` along the bas-relief trade
        scores better than the fit (:func:`best_turned`, :func:`turned_reason`): ambiguous, since the fit is not the
        optimum of its own objective along the trade, and its direction may be off by that much or more.
    flat_valley : bool
        se3 with a free rotation: a motion ``QualitySettings.bas_relief_valley_deg`` along the bas-relief trade
        scores within noise of the fit (:func:`valley_turned`, :func:`valley_reason`): ambiguous, since the events
        do not fix the translation direction (nor the size of the rotation and the depth's scale) to within that
        angle.
    """

    verdict: Verdict
    reason: str
    alternatives: tuple[Alternative, ...] = ()
    resolution: str = ""
    resolved: bool = False
    replaced: tuple[np.ndarray, np.ndarray] | None = None
    cause: LowMotionCause | None = None
    rate_change: float | None = None
    unsteady: bool = False
    sparse: bool = False
    on_bound: bool = False
    small_parallax: bool = False
    noisy: bool = False
    noise_share: float | None = None
    turned: bool = False
    flat_valley: bool = False

    def summary(self) -> dict:
        """A JSON-ready dict (an infinite ``rate_change``, one half of the window without events, as None with
        ``unsteady`` True)."""
        rate = None if self.rate_change is None or not math.isfinite(self.rate_change) else self.rate_change
        return {"verdict": self.verdict.value, "reason": self.reason,
                "cause": None if self.cause is None else self.cause.value,
                "rate_change": rate, "unsteady": self.unsteady, "sparse": self.sparse, "on_bound": self.on_bound,
                "small_parallax": self.small_parallax, "noisy": self.noisy, "noise_share": self.noise_share, "turned": self.turned,
                "flat_valley": self.flat_valley,
                "alternatives": [{"name": a.name, "v": a.v.tolist(), "omega": a.omega.tolist(), "gain": a.gain,
                                  "noise": a.noise, "within_noise": a.within_noise} for a in self.alternatives],
                "resolution": self.resolution, "resolved": self.resolved,
                "replaced": None if self.replaced is None else {"v": self.replaced[0].tolist(),
                                                                 "omega": self.replaced[1].tolist()}}


# ----------------------------------------------------------------------------------------------
# Alternatives and their scores
# ----------------------------------------------------------------------------------------------
def _unit_flows(rays: torch.Tensor, K: torch.Tensor, rho: torch.Tensor, v: np.ndarray,
                dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Flows [px over ``dt``] of the translation ``v`` at inverse depths ``rho`` (M,), and of the unit
    rotations about x, y, z: (2M,) and (2M, 3), by the exact warp (its conventions, not a formula's)."""
    dtype = rays.dtype
    t = torch.full((1, rays.shape[0]), dt, dtype=dtype)
    zero = torch.zeros(3, dtype=dtype)
    x0, y0 = warp_se3(rays, t * 0, zero, zero, rho, K)

    def flow(v_, omega_):
        x, y = warp_se3(rays, t, torch.as_tensor(v_, dtype=dtype), torch.as_tensor(omega_, dtype=dtype), rho, K)
        return torch.cat([(x - x0)[0], (y - y0)[0]]).double().numpy()

    rotation = np.stack([flow(zero, torch.eye(3, dtype=dtype)[k]) for k in range(3)], 1)
    return flow(v, zero), rotation


def _patch_samples(objective: LocalMotionObjective, rho: np.ndarray,
                   samples: int = 2000) -> tuple[torch.Tensor, torch.Tensor]:
    """About ``samples`` of the patches' events, evenly through them: their rays (M, 3) and the inverse depth
    (M,) [1/m] of each one's patch (``rho`` (P,) [1/m]), on which the alternatives' least squares run."""
    step = max(1, len(objective.patches.x) // samples)
    return (objective.rays[::step],
            torch.as_tensor(rho, dtype=objective.rays.dtype)[objective.patches.patch[::step]])


def alternative_motions(objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray, rho: np.ndarray,
                        *, hold_omega: bool) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The alternatives of the fit ``(v, omega)`` with patch inverse depths ``rho`` (P,) [1/m]:
    ``mirrored`` ``(-v, omega)``; unless ``hold_omega``, ``rotation_flipped`` ``(v, -omega)`` and
    ``bas_relief`` ``(-v, omega + d)`` with ``d`` the rotation whose flow best matches (least squares
    over the patches' events) twice the translation's flow, so that ``-v`` with it moves the events as
    the fit does; and ``planar_dual`` (:func:`_planar_dual`), the other motion of the patches' best plane."""
    v, omega = np.asarray(v, float), np.asarray(omega, float)
    out = [("mirrored", -v, omega.copy())]
    if hold_omega:
        return out
    if np.linalg.norm(omega) > 0:
        out.append(("rotation_flipped", v.copy(), -omega))
    rays, rho_events = _patch_samples(objective, rho)
    dt = 1e-3
    translation, rotation = _unit_flows(rays, objective.K, rho_events, v, dt)
    d, *_ = np.linalg.lstsq(rotation, 2.0 * translation, rcond=None)
    out.append(("bas_relief", -v, omega + d))
    dual = _planar_dual(rays, objective.K, rho_events, v, omega, translation, rotation, dt)
    if dual is not None:
        out.append(("planar_dual", *dual))
    return out


def _planar_dual(rays: torch.Tensor, K: torch.Tensor, rho: torch.Tensor, v: np.ndarray, omega: np.ndarray,
                 translation: np.ndarray, rotation: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray] | None:
    """The other motion of a planar scene: a plane ``rho = q . ray`` (the least-squares plane of the events'
    inverse depths ``rho`` (M,) [1/m] on their ``rays`` (M, 3), ``K^-1 (x, y, 1)``) seen under ``(v, omega)``
    moves its points as the plane ``q' = sigma |q| v / s`` seen under ``v' = sigma s q / |q|`` (``s = |v|``,
    ``sigma`` the sign that keeps most of ``q'`` in front), with a rotation that makes up the rest: the two
    solutions of the planar motion field (Longuet-Higgins, Proc. R. Soc. B 1984; Subbarao and Waxman, CVGIP
    1986): the image motion of a plane depends on ``v`` and its normal only through ``v q^T``, whose symmetric
    part is the same for both. The rotation is fitted (least squares over the events) so that ``(v', omega')``
    at ``q'`` moves the events as the fit does, by the exact warp's flows: ``translation`` (2M,) of ``v`` at
    ``rho`` and the unit rotations' ``rotation`` (2M, 3), over ``dt`` [s]. A fronto-parallel wall under a sideways
    slide has the forward motion as its dual: the fit can settle there, turning the slide into rotation. None when
    the plane or the speed is degenerate."""
    A, r = rays.double().numpy(), rho.double().numpy()
    q, *_ = np.linalg.lstsq(A, r, rcond=None)
    s, size = float(np.linalg.norm(v)), float(np.linalg.norm(q))
    if not (s > 0 and size > 0 and np.isfinite(size)):
        return None
    sigma = 1.0 if float(np.median(A @ v)) >= 0 else -1.0
    v_dual = sigma * s * q / size
    rho_dual = np.maximum(sigma * size / s * (A @ v), 1e-6 * float(np.median(np.abs(r))))   # in front
    moved, _ = _unit_flows(rays, K, torch.as_tensor(rho_dual, dtype=rays.dtype), v_dual, dt)
    d, *_ = np.linalg.lstsq(rotation, translation - moved, rcond=None)
    return v_dual, np.asarray(omega, float) + d


def _patch_contrast(objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray,
                    candidates: np.ndarray, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Per-patch normalised contrast (P,) of ``(v, omega)`` with each patch's best inverse depth among
    ``candidates`` [1/m] (swept with ``stride``, :meth:`LocalMotionObjective.sweep_rho`), and those depths (P,)."""
    rho = objective.sweep_rho(v, omega, candidates, stride)
    with torch.no_grad():
        values = objective.values(torch.from_numpy(objective.params(v, omega, rho))).double().numpy()
    return values, rho


@dataclass(frozen=True, eq=False)
class MotionScorer:
    """Scores other motions of a window against its fit ``(v, omega)``: the gain and noise of the module
    docstring, each motion with its own per-patch inverse-depth sweep. Built by :meth:`build`."""

    objective: LocalMotionObjective
    candidates: np.ndarray
    c_fit: np.ndarray
    rho: np.ndarray
    settings: QualitySettings
    stride: int = 1

    @classmethod
    def build(cls, w, v: np.ndarray, omega: np.ndarray, speed: float,
              settings: QualitySettings) -> "MotionScorer | None":
        """The scorer of the fit ``(v (3,) [m/s], omega (3,) [rad/s])`` of window ``w`` (a
        :class:`cmax.fitting.window.Window`) with ``|v| = speed``; None when fewer than
        ``w.settings.refine.min_patches`` patches (at least 2) hold events."""
        refine = w.settings.refine
        patches = make_patches(w, grid=refine.grid, min_events=refine.min_events, max_events=refine.max_events,
                               margin=refine.margin, min_margin_px=refine.min_margin_px)
        if patches is None or patches.count < max(refine.min_patches, 2):
            return None
        objective = LocalMotionObjective.build(w, patches, speed)
        near, far = w.settings.depth_range
        candidates = np.exp(np.linspace(np.log(1.0 / far), np.log(1.0 / near), refine.rho_candidates))
        stride = sweep_stride(refine, w.settings.depth_range)
        c_fit, rho = _patch_contrast(objective, np.asarray(v, float), np.asarray(omega, float), candidates, stride)
        return cls(objective, candidates, c_fit, rho, settings, stride)

    @property
    def own_gain(self) -> float:
        """The fit's summed normalised contrast over the unwarped events (``sum_p (c_p - 1)``)."""
        return float(np.sum(self.c_fit - 1.0))

    def score(self, name: str, v: np.ndarray, omega: np.ndarray) -> Alternative:
        """``(v (3,), omega (3,))`` as an :class:`Alternative` of the fit: summed gain, noise, within noise."""
        c_alt, _ = _patch_contrast(self.objective, np.asarray(v, float), np.asarray(omega, float), self.candidates,
                                   self.stride)
        gain = self.c_fit - c_alt
        noise = max(self.settings.noise_sigmas * float(np.std(gain, ddof=1)) * math.sqrt(len(gain)),
                    self.settings.margin * max(self.own_gain, 0.0))
        return Alternative(name, np.asarray(v, float), np.asarray(omega, float), float(gain.sum()), noise,
                           bool(gain.sum() <= noise))


def assess(w, v: np.ndarray, omega: np.ndarray, speed: float, settings: QualitySettings, solver, *,
           hold_omega: bool, scorer: MotionScorer | None = None) -> tuple[tuple[Alternative, ...], str, bool]:
    """The ambiguity test of a se3 fit ``(v, omega)`` of window ``w`` (a :class:`cmax.fitting.window.Window`),
    polishing the alternatives with ``solver`` (a :class:`cmax.fitting.solvers.Solver`); ``scorer``: the fit's
    :meth:`MotionScorer.build` of these arguments when the caller holds it (the bas-relief turn scores on the same
    one, :func:`best_turned`), None: built here.

    Returns ``(alternatives, note, tested)``: ``tested`` False, no alternatives and ``note`` saying why when
    the window has fewer than ``w.settings.refine.min_patches`` patches with events (nothing to test on: the
    verdict cannot be ``ok``); ``note`` also names the alternatives dropped because their polish ended on
    the fit (within ``settings.distinct_deg``), but for those that end at least ``settings.recheck_deg`` from it
    and score better than the fit by more than ``settings.margin`` times its own gain (more than a tie): they are
    kept (the fit is then not the optimum of its own objective).
    """
    scorer = MotionScorer.build(w, v, omega, speed, settings) if scorer is None else scorer
    if scorer is None:
        return (), (f"ambiguity not tested: fewer than {max(w.settings.refine.min_patches, 2)} patches hold "
                    "events"), False
    refine = w.settings.refine
    alternatives, merged = [], []
    self_margin = settings.margin * max(scorer.own_gain, 0.0)     # "better than the fit" beyond a tie
    for name, v_alt, omega_alt in alternative_motions(scorer.objective, v, omega, scorer.rho, hold_omega=hold_omega):
        if settings.polish_iterations:
            polished = refine_motion_local(w, v_alt, omega_alt, speed,
                                           replace(refine, iterations=settings.polish_iterations),
                                           solver, hold_omega=hold_omega, objective=scorer.objective)
            v_alt, omega_alt = polished.v, polished.omega
            distance = _distance_deg(v_alt, omega_alt, v, omega, w.T)
            if distance < settings.distinct_deg:
                scored = scorer.score(name, v_alt, omega_alt) if distance >= settings.recheck_deg else None
                if scored is None or not scored.gain < -self_margin:
                    merged.append(name)
                    continue
                alternatives.append(scored)                 # near the fit, but better: the fit is no optimum
                continue
        alternatives.append(scorer.score(name, v_alt, omega_alt))
    note = f"the {', '.join(merged)} alternative(s) polished back onto the fit" if merged else ""
    return tuple(alternatives), note, True


# ----------------------------------------------------------------------------------------------
# Is the fit the optimum of its own objective along the bas-relief trade? (se3, rotation free)
# ----------------------------------------------------------------------------------------------
def turned_motions(objective: LocalMotionObjective, v: np.ndarray, omega: np.ndarray, rho: np.ndarray,
                   degrees: float) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """The fit ``(v (3,) [m/s], omega (3,) [rad/s])`` moved ``degrees`` along the bas-relief trade, four ways: ``v``
    turned by ``degrees`` towards ``+a``, ``-a``, ``+b`` and ``-b`` (``a``, ``b``: unit vectors perpendicular to
    ``v`` and to each other), its speed kept, each with the rotation ``omega + d``, ``d`` the rotation whose flow
    best makes up (least squares over the patches' events, at the patch inverse depths ``rho`` (P,) [1/m]) the
    change of the translation's flow, so that the turned motion moves the events nearly as the fit does. Named
    ``turned_+a`` ... ``turned_-b``."""
    v, omega = np.asarray(v, float), np.asarray(omega, float)
    speed = float(np.linalg.norm(v))
    u = v / speed
    a = np.cross(u, [1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.cross(u, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    rays, rho_events = _patch_samples(objective, rho)
    dt, angle = 1e-3, math.radians(degrees)
    translation, rotation = _unit_flows(rays, objective.K, rho_events, v, dt)
    out = []
    for name, e in (("+a", a), ("-a", -a), ("+b", b), ("-b", -b)):
        v_turned = speed * (math.cos(angle) * u + math.sin(angle) * e)
        moved, _ = _unit_flows(rays, objective.K, rho_events, v_turned, dt)
        d, *_ = np.linalg.lstsq(rotation, translation - moved, rcond=None)
        out.append((f"turned_{name}", v_turned, omega + d))
    return out


def best_turned(w, v: np.ndarray, omega: np.ndarray, speed: float, settings: QualitySettings,
                scorer: MotionScorer | None = None) -> Alternative | None:
    """The best-scoring of the fit's :func:`turned_motions` by ``settings.bas_relief_turn_deg``, scored as an
    :class:`Alternative` of the fit ``(v (3,) [m/s], omega (3,) [rad/s])`` of window ``w`` (a
    :class:`cmax.fitting.window.Window`, ``|v| = speed``) by :class:`MotionScorer`: ``scorer``, the fit's
    :meth:`MotionScorer.build` of these arguments when the caller holds it (the ambiguity test's, :func:`assess`),
    None: built here. None when the window has too few patches to score on, or the test is off
    (``bas_relief_turn_deg`` 0) or the speed is 0."""
    scored = _scored_turns(w, v, omega, speed, settings, settings.bas_relief_turn_deg, scorer)
    return None if scored is None else min(scored, key=lambda a: a.gain)


def _scored_turns(w, v: np.ndarray, omega: np.ndarray, speed: float, settings: QualitySettings, degrees: float,
                  scorer: MotionScorer | None) -> list[Alternative] | None:
    """The fit's four :func:`turned_motions` by ``degrees`` scored by ``scorer`` (built here when None) as
    :class:`Alternative` s; None when ``degrees`` is 0, the speed is 0 or the window has too few patches."""
    if not degrees > 0 or not np.linalg.norm(v) > 0:
        return None
    scorer = MotionScorer.build(w, v, omega, speed, settings) if scorer is None else scorer
    if scorer is None:
        return None
    return [scorer.score(name, v_turned, omega_turned) for name, v_turned, omega_turned
            in turned_motions(scorer.objective, v, omega, scorer.rho, degrees)]


def turned_reason(turned: Alternative | None, degrees: float) -> str:
    """The reason of a window whose fit a motion ``degrees`` along the bas-relief trade (:func:`best_turned`:
    ``turned``, None when not scored) scores better than (its gain under 0), "" otherwise.

    >>> turned_reason(Alternative("turned_+a", np.ones(3), np.zeros(3), -0.2, 0.5, True), 10.0)[:71]
    'a motion turned 10 deg along the bas-relief trade (turned_+a) scores be'
    >>> turned_reason(Alternative("turned_+a", np.ones(3), np.zeros(3), 0.1, 0.5, True), 10.0)
    ''
    """
    if turned is None or not turned.gain < 0:
        return ""
    return (f"a motion turned {degrees:g} deg along the bas-relief trade ({turned.name}) scores better than the fit "
            f"(gain {turned.gain:.3g} < 0; bas_relief_turn_deg={degrees:g}): the fit is not the optimum of its own "
            "objective along the trade of the translation for a rotation, so its direction and its rotation's size, "
            "and with them the depth, may be off by that much or more")


def valley_turned(w, v: np.ndarray, omega: np.ndarray, speed: float, settings: QualitySettings,
                  scorer: MotionScorer | None = None) -> Alternative | None:
    """The fit's :func:`turned_motions` by ``settings.bas_relief_valley_deg``, scored as :class:`Alternative` s of the
    fit ``(v (3,) [m/s], omega (3,) [rad/s])`` of window ``w`` (a :class:`cmax.fitting.window.Window`, ``|v| =
    speed``) by :class:`MotionScorer`: the one that scores nearest the fit, or beyond it, relative to its noise
    (the least ``gain - noise``); ``scorer``: the fit's :meth:`MotionScorer.build` of these arguments when the
    caller holds it (the ambiguity test's), None: built here. None when the window has too few patches to score on,
    the test is off (``bas_relief_valley_deg`` 0) or the speed is 0."""
    scored = _scored_turns(w, v, omega, speed, settings, settings.bas_relief_valley_deg, scorer)
    return None if scored is None else min(scored, key=lambda a: a.gain - a.noise)


def valley_reason(turned: Alternative | None, degrees: float) -> str:
    """The reason of a window whose fit a motion ``degrees`` along the bas-relief trade (:func:`valley_turned`:
    ``turned``, None when not scored) scores within noise of (its gain at most its noise), "" otherwise.

    >>> valley_reason(Alternative("turned_+a", np.ones(3), np.zeros(3), 0.08, 0.43, True), 20.0)[:72]
    'a motion turned 20 deg along the bas-relief trade (turned_+a) scores wit'
    >>> valley_reason(Alternative("turned_+a", np.ones(3), np.zeros(3), 0.6, 0.43, False), 20.0)
    ''
    """
    if turned is None or not turned.gain <= turned.noise:
        return ""
    return (f"a motion turned {degrees:g} deg along the bas-relief trade ({turned.name}) scores within noise of the "
            f"fit (gain {turned.gain:.3g} <= noise {turned.noise:.3g}; bas_relief_valley_deg={degrees:g}): the events "
            f"do not fix the translation direction to within {degrees:g} deg, where a rotation of another size makes "
            "up the difference, nor with it the rotation and the depth's scale")


# ----------------------------------------------------------------------------------------------
# Is the fitted motion measured at all? (flow and rotation: the cell-noise test; every model: the permutation test)
# ----------------------------------------------------------------------------------------------
def _cell_gains(w, cells: tuple[int, int], *warped: tuple[torch.Tensor, torch.Tensor],
                index: slice = slice(None)) -> list[tuple[np.ndarray, np.ndarray]]:
    """For each ``(x, y)`` (B, N) [px] of ``warped``: each cell's share (C,) of its normalised contrast gain
    over ``w``'s unwarped events (they sum to ``objective_after - 1``), and which cells (C,) hold events in
    either; on the events ``index`` selects (all by default)."""
    ev, s = w.ev, w.settings
    H, W, kind = ev.height, ev.width, s.contrast or "variance"
    on = None if w.on is None else w.on[..., index]

    def shares(xw: torch.Tensor, yw: torch.Tensor) -> torch.Tensor:
        xw, yw = xw[:, index], yw[:, index]
        if on is None:
            images = blur(accumulate_bilinear(xw, yw, None, H, W), s.sigma)
        else:
            images = polarity_images(xw, yw, on, H, W, s.sigma)
        return contrast_by_cell(images, kind, cells).sum(0) / xw.shape[0]   # mean over references

    with torch.no_grad():
        before = shares(ev.x[None], ev.y[None])
        total = max(float(before.sum()), 1e-300)
        out = []
        for x, y in warped:
            after = shares(x, y)
            out.append((((after - before) / total).double().numpy(), ((before > 0) | (after > 0)).numpy()))
    return out


def shuffled_gain_test(w, x: torch.Tensor, y: torch.Tensor, x_shuffled: torch.Tensor, y_shuffled: torch.Tensor,
                       settings: QualitySettings) -> tuple[float, float, bool]:
    """The permutation test of every model (see the module docstring): ``(G, G_shuffled, not measured)``.

    ``x, y`` (B, N) [px]: ``w``'s events warped by the fitted motion to the ``B`` reference times of
    ``w.dt``; ``x_shuffled, y_shuffled`` (B, N): the same events warped by the same motion with their time
    offsets ``w.dt`` permuted among the events. Not measured when ``G <= 0`` or ``G_shuffled >=
    settings.shuffle_fraction * G``. Both gains are taken on every k-th event, k the smallest stride that
    leaves at most ``settings.shuffle_events`` (the same subset for the unwarped, fitted and shuffled images).
    """
    stride = max(1, -(-x.shape[1] // settings.shuffle_events))
    (fitted, _), (permuted, _) = _cell_gains(w, settings.motion_cells, (x, y), (x_shuffled, y_shuffled),
                                             index=slice(None, None, stride))
    gain, shuffled = float(fitted.sum()), float(permuted.sum())
    return gain, shuffled, bool(gain <= 0 or shuffled >= settings.shuffle_fraction * gain)


def motion_within_noise(w, x: torch.Tensor, y: torch.Tensor, settings: QualitySettings) -> tuple[float, float, bool]:
    """The low-motion test of a flow or rotation fit (see the module docstring): ``(G, noise, G <= noise)``.

    ``w`` is the fit's :class:`cmax.fitting.window.Window` (its contrast kind, blur and polarity split);
    ``x, y`` (B, N) [px] its events warped by the fitted motion to the ``B`` reference times of
    ``w.dt``. ``G`` is the normalised contrast gain over the unwarped events (``objective_after - 1``),
    ``noise`` ``settings.motion_noise_sigmas`` standard errors of it over ``settings.motion_cells``.
    """
    ((gain, used),) = _cell_gains(w, settings.motion_cells, (x, y))
    gain = gain[used]
    G = float(gain.sum())
    if gain.size < 2:
        return G, float("inf"), True
    noise = settings.motion_noise_sigmas * float(np.std(gain, ddof=1)) * math.sqrt(gain.size)
    return G, noise, bool(G <= noise)


# ----------------------------------------------------------------------------------------------
# Is the motion steady over the window? (se3)
# ----------------------------------------------------------------------------------------------
def rate_change(t_us: np.ndarray) -> float:
    """How unevenly a window's events fill its time: the events in the busier half of ``[t[0], t[-1]]`` over
    those in the other half (an event at the midpoint counts in the second). 1 for a steady rate; inf when one
    half holds none; 1 for fewer than two events or a single time stamp. ``t_us`` (N,) sorted [µs].

    >>> import numpy as np
    >>> rate_change(np.array([0, 10, 20, 30, 40, 50, 60, 70, 80, 100]))      # 5 and 5 events
    1.0
    >>> rate_change(np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 100]))              # a stop: 9 events, then 1
    9.0
    """
    t = np.asarray(t_us)
    if t.size < 2 or t[-1] == t[0]:
        return 1.0
    first = int(np.searchsorted(t, t[0] + (t[-1] - t[0]) / 2, side="left"))
    low, high = sorted((first, t.size - first))
    return math.inf if low == 0 else high / low


def _unsteady_reason(rate: float, max_rate_change: float) -> str:
    """The reason of an unsteady window (:func:`rate_change` ``rate`` over ``max_rate_change``), "" otherwise."""
    if not rate > max_rate_change:
        return ""
    how = "one half of the window holds no event" if math.isinf(rate) else \
        f"the event rate changes {rate:.1f}x between the window's halves"
    return (f"{how} (over max_rate_change={max_rate_change:g}): the motion is not steady over the window (a start, "
            "a stop, something entering the view), so no single motion explains its events")


def density_pixels(width: int, height: int, density_area: int = 346 * 260) -> float:
    """The pixels [px] over which :func:`sparse_reason` counts the events of a ``width`` x ``height`` window: the
    image's own up to ``density_area`` (``QualitySettings.min_event_density_area``), beyond it the geometric mean
    ``sqrt(width * height * density_area)``. A scene's events lie along its edges, whose length in pixels grows
    with the image's side, not with its area, so a larger image of the same view spreads as many events over
    its edges' pixels as the square root of its area says (docs/quality.md: the measurement).

    >>> density_pixels(346, 260), density_pixels(160, 120), round(density_pixels(1280, 720))
    (89960.0, 19200.0, 287936)
    """
    area = width * height
    return float(area) if area <= density_area else math.sqrt(area * density_area)


def sparse_reason(fitted: int, given: int, width: int, height: int, min_event_density: float,
                  density_area: int = 346 * 260) -> str:
    """The reason of a window too sparse to vouch for its direction, "" otherwise: ``fitted`` events (of ``given``;
    fewer when ``FitSettings.max_events`` subsampled them) on a ``width`` x ``height`` image, under
    ``min_event_density`` events per pixel of :func:`density_pixels` (the image's pixels up to ``density_area``,
    ``QualitySettings.min_event_density_area``; beyond it fewer). Nearly every event then lies alone in its
    pixel, and the contrast of a wrong direction can beat its mirrored and rotation-swapped alternatives by
    more than their noise.

    >>> sparse_reason(3000, 3000, 346, 260, 0.25)[:60]
    '3,000 events on 346x260 pixels (0.033 per pixel, under min_e'
    >>> sparse_reason(60_000, 60_000, 346, 260, 0.25)
    ''
    >>> sparse_reason(60_000, 60_000, 640, 480, 0.25)
    ''
    >>> sparse_reason(60_000, 219_596, 1280, 720, 0.25)[:74]
    '60,000 events on 1280x720 pixels (0.208 per pixel of sqrt(1280 x 720 x min'
    """
    pixels = density_pixels(width, height, density_area)
    density = fitted / pixels
    if not density < min_event_density:
        return ""
    more = (f"; {given:,} were given: a larger FitSettings.max_events (cmax fit: --max-events) fits more of them"
            if given > fitted else "; a longer window gives more events")
    per = ("per pixel" if width * height <= density_area else
           f"per pixel of sqrt({width} x {height} x min_event_density_area={density_area:,}) = {pixels:,.0f} px")
    return (f"{fitted:,} events on {width}x{height} pixels ({density:.3f} {per}, under min_event_density="
            f"{min_event_density:g}): too sparse for the contrast to vouch for the direction{more}")


def isolated_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, height: int, window_us: int,
                    radius: int = 1) -> np.ndarray:
    """Events (N,) bool with no other event within ``radius`` pixels (a ``2 radius + 1`` square, their own pixel
    included) and ``window_us`` µs on either side: the test of the background-activity filter (Delbruck 2008;
    Guo & Delbruck 2022), exact rather than with a timestamp map. ``x, y`` (N,) integer pixels inside the
    ``width`` x ``height`` image, ``t`` (N,) µs. Vectorized: a sorted key per event, the own pixel read off the
    keys next to the event's, and one binary search per other neighbour pixel.

    >>> isolated_events(np.array([0, 1, 5]), np.array([0, 0, 5]), np.array([0, 500, 600]), 8, 8, 1000).tolist()
    [False, False, True]
    """
    _check_pixels(x, y, t, width, height, window_us, radius)
    return _isolated(_sorted_events(x, y, t, width, window_us), width, height, window_us, radius)


def _check_pixels(x: object, y: object, t: object, width: int, height: int, window_us: object = 0,
                  radius: object = 0, max_queries: object = None) -> None:
    """Refuse events ``x, y, t`` that are not three 1-D arrays of one length, pixels ``x, y`` that are not whole
    numbers inside the ``width`` x ``height`` image (a pixel off the image would be read as one of the next row's),
    a ``window_us`` or ``radius`` that is not a whole number >= 0, or a ``max_queries`` that is not None or >= 1."""
    for name, value, least in (("window_us", window_us, 0), ("radius", radius, 0),
                               ("max_queries", 1 if max_queries is None else max_queries, 1)):
        if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= least):
            raise ValueError(f"{name} must be a whole number >= {least}{' or None' if name == 'max_queries' else ''}, "
                             f"got {value!r}")
    shapes = [np.shape(a) for a in (x, y, t)]
    if len(shapes[0]) != 1 or len(set(shapes)) != 1:
        raise ValueError(f"x, y and t must be 1-D arrays of one length, got shapes {shapes[0]}, {shapes[1]} and "
                         f"{shapes[2]}")
    for name, values, size in (("x", np.asarray(x), width), ("y", np.asarray(y), height)):
        if not values.size:
            continue
        if values.dtype == bool or not np.issubdtype(values.dtype, np.number):
            raise ValueError(f"{name} must hold whole pixels, got {values.dtype} values")
        if not np.issubdtype(values.dtype, np.integer):
            fractional = np.flatnonzero(values != np.floor(values))
            if fractional.size:
                raise ValueError(f"{name} must hold whole pixels, got {values[fractional[0]]:g}")
        low, high = values.min(), values.max()
        if low < 0 or high >= size:
            raise ValueError(f"{name} must hold pixels in [0, {size - 1}] of the {width}x{height} image, got "
                             f"{low:g} to {high:g}")


class _Sorted(NamedTuple):
    """Events sorted by pixel, then time (:func:`_sorted_events`): ``x, y`` (N,) int64 [px], ``keys`` (N,) int64
    (``pixel * span + t``, the times shifted so that two pixels' keys never overlap within the window), ``order``
    (N,) the sorting permutation, ``span`` the keys' stride per pixel."""

    x: np.ndarray
    y: np.ndarray
    keys: np.ndarray
    order: np.ndarray
    span: int


def _isolated(events: _Sorted, width: int, height: int, window_us: int, radius: int) -> np.ndarray:
    """:func:`isolated_events` of the sorted ``events`` (:func:`_sorted_events` with this ``window_us``), in the
    events' given order: (N,) bool."""
    isolated = np.empty(events.keys.size, bool)
    isolated[events.order] = _alone(events, np.arange(events.keys.size), width, height, window_us, radius)
    return isolated


def neighbour_counts(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, height: int, window_us: int,
                     radius: int = 1) -> np.ndarray:
    """How many other events (N,) int64 each event has within ``radius`` pixels (a ``2 radius + 1`` square, its own
    pixel included) and ``window_us`` µs on either side: the neighbour support of the background-activity filter
    (Delbruck 2008; Guo & Delbruck 2022), 0 exactly where :func:`isolated_events` is True. ``x, y`` (N,) integer
    pixels inside the ``width`` x ``height`` image, ``t`` (N,) µs. Two binary searches per neighbour pixel.

    >>> neighbour_counts(np.array([0, 1, 1, 5]), np.array([0, 0, 1, 5]), np.array([0, 500, 900, 600]), 8, 8,
    ...                  1000).tolist()
    [2, 2, 2, 0]
    """
    _check_pixels(x, y, t, width, height, window_us, radius)
    return _neighbour_counts(_sorted_events(x, y, t, width, window_us), width, height, window_us, radius)


def _neighbour_counts(events: _Sorted, width: int, height: int, window_us: int, radius: int) -> np.ndarray:
    """:func:`neighbour_counts` (N,) int64 of the sorted ``events`` (:func:`_sorted_events` with this
    ``window_us``), in the events' given order."""
    keys, x, y = events.keys, events.x, events.y
    counts = np.zeros(keys.size, np.int64)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            inside = (x + dx >= 0) & (x + dx < width) & (y + dy >= 0) & (y + dy < height)
            base = keys + (dy * width + dx) * events.span
            found = np.searchsorted(keys, base + window_us, "right") - np.searchsorted(keys, base - window_us, "left")
            counts += np.where(inside, found, 0)
    out = np.empty_like(counts)
    out[events.order] = counts - 1                                         # not the event itself
    return out


def _sorted_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, window_us: int) -> _Sorted:
    """The events ``x, y, t`` (N,) [px, px, µs] sorted by pixel, then time (stable), as a :class:`_Sorted`."""
    x, y, t = (np.asarray(a, np.int64) for a in (x, y, t))
    if x.size:
        t = t - int(t.min()) + window_us + 1
    span = (int(t.max()) if t.size else 0) + window_us + 1
    pixel = y * width + x
    order = _pixel_time_order(pixel, t)
    return _Sorted(x[order], y[order], (pixel * span + t)[order], order, span)


def _sorted_subset(events: _Sorted, keep: np.ndarray) -> _Sorted:
    """The sorted ``events`` (:func:`_sorted_events`) of the subset ``keep`` (N,) bool (in the events' given order),
    without sorting again: a subsequence of the sorted keys is sorted, and the keys keep the whole set's time shift
    and ``span``, which hold the subset's times apart per pixel as well, so :func:`_alone` and
    :func:`_neighbour_counts` give what they give on the subset sorted anew; ``order`` indexes the subset."""
    keep = np.asarray(keep, bool)
    chosen = keep[events.order]                                          # in the sorted order
    position = np.cumsum(keep) - 1                                       # index of each kept event in the subset
    return _Sorted(events.x[chosen], events.y[chosen], events.keys[chosen], position[events.order[chosen]],
                   events.span)


def _pixel_time_order(pixel: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The stable sorting permutation (N,) of the events by ``pixel`` (N,) int64 >= 0, then ``t`` (N,): the same
    as ``np.argsort(pixel * span + t, kind="stable")`` (the keys of :func:`_sorted_events`), by a least-significant-
    digit radix sort: the time order first (none when ``t`` is sorted already, as an ``Events``' times are), then
    stable passes over the pixel's 16-bit digits."""
    # Written out instead of np.argsort(keys, kind="stable") because numpy sorts 16-bit integers by radix but int64
    # keys by timsort: on 331k events of a 346x260 window 6.5 ms against 34 ms (Xeon, 2026-12-05); the same order.
    order = np.arange(t.size) if t.size < 2 or bool(np.all(t[1:] >= t[:-1])) else np.argsort(t, kind="stable")
    top = int(pixel.max()) if pixel.size else 0
    shift = 0
    while True:
        digit = ((pixel[order] >> shift) & 0xFFFF).astype(np.uint16)
        order = order[np.argsort(digit, kind="stable")]
        shift += 16
        if top >> shift <= 0:
            return order


def _alone(events: _Sorted, at: np.ndarray, width: int, height: int, window_us: int, radius: int) -> np.ndarray:
    """Whether each queried event (its position ``at`` (Q,) in the sorted ``events``, :func:`_sorted_events`) has no
    event but itself within ``radius`` pixels and ``window_us`` µs: (Q,) bool. The own pixel first: its events are
    neighbours in the sorted keys, so the keys before and after settle it (the pixels' keys never overlap within
    ``window_us``); then one search per neighbour pixel, each only for the events still alone: the first key at or
    after ``t - window_us`` in that pixel lies within ``t + window_us`` exactly when the pixel holds such an event."""
    keys, last = events.keys, events.keys.size - 1
    query = keys[at]
    before = (at > 0) & (keys[np.maximum(at - 1, 0)] >= query - window_us)
    after = (at < last) & (keys[np.minimum(at + 1, last)] <= query + window_us)
    pending = np.flatnonzero(~(before | after))          # the events still alone, and their pixels and keys
    x, y, query = events.x[at[pending]], events.y[at[pending]], query[pending]
    offsets = sorted(((dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
                      if (dy, dx) != (0, 0)), key=lambda o: abs(o[0]) + abs(o[1]))   # the nearest first
    for dy, dx in offsets:
        todo = np.flatnonzero((x + dx >= 0) & (x + dx < width) & (y + dy >= 0) & (y + dy < height))
        if not todo.size:
            continue
        base = query[todo] + (dy * width + dx) * events.span
        first = np.searchsorted(keys, base - window_us, "left")
        found = (first <= last) & (keys[np.minimum(first, last)] <= base + window_us)
        still = np.ones(pending.size, bool)
        still[todo[found]] = False
        pending, x, y, query = pending[still], x[still], y[still], query[still]
    alone = np.zeros(at.size, bool)
    alone[pending] = True
    return alone


def noise_share(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, height: int, window_us: int,
                radius: int = 1, max_queries: int | None = 60_000, isolated: np.ndarray | None = None) -> float:
    """Estimated share of uniform background-activity (shot) noise among the window's events ``x, y, t`` (N,)
    [px, px, µs] on a ``width`` x ``height`` image, in [0, 1]. ``max_queries``: at most this many events (a seeded
    uniform subset; None: all) are tested for neighbours, each against all N events, and the isolated counts are
    scaled by N over their number (an unbiased estimate: the test of one event does not depend on which others
    are tested), so a window of millions of events costs one sort and that many searches. ``isolated`` (N,) bool:
    :func:`isolated_events` of these events with this ``window_us`` and ``radius``, when the caller has it (the
    fit's depth mask does): taken as is, none tested again.

    Noise of ``r`` Hz per pixel, uniform in space and time, leaves an event without a neighbour
    (:func:`isolated_events`) with probability ``exp(-r V)``, ``V = (2 radius + 1)^2 * 2 window_us`` [px s]
    (the time span cut by the window's ends: less on a window shorter than a few ``window_us``);
    so the isolated events per pixel and second, ``m``, satisfy ``m = r exp(-r V)``: two rates, ``-W0(-m V) / V``
    and ``-W-1(-m V) / V`` (the two branches of Lambert W; one rate, ``1 / V``, past ``m V = 1/e``), since heavy
    noise leaves few events alone. The events isolated within ``radius + 1`` pixels tell them apart (a wider
    square, not a longer time, so that it works on windows shorter than ``window_us`` too): the rate whose
    predicted count of those lies closer (in ratio) to the measured one is taken. The share is that
    rate times the pixels and the window's duration over ``N``. Events of the scene that lie alone (sparse edges,
    a slow scene) count as noise, so a clean window reads above 0 (0.01-0.12 on the synthetic presets at
    160x120, 0.04-0.06 at 346x260, 0.05 and 0.09 on the real DAVIS346 and Gen4 samples); noise near events of the
    scene goes unseen, and more of it does at high rates, so a noisy window can read below its true share
    (docs/quality.md: the measurement).

    >>> rng = np.random.default_rng(0)
    >>> n = rng.poisson(1.0 * 160 * 120 * 0.1)                              # 1 Hz per pixel over 0.1 s
    >>> share = noise_share(rng.integers(0, 160, n), rng.integers(0, 120, n), np.sort(rng.integers(0, 100_000, n)),
    ...                     160, 120, 10_000)
    >>> 0.8 < share <= 1.0
    True
    """
    _check_pixels(x, y, t, width, height, window_us, radius, max_queries)
    t = np.asarray(t, np.int64)
    if t.size < 2 or t[-1] == t[0]:
        return 0.0
    return _noise_share(_sorted_events(x, y, t, width, window_us), t, width, height, window_us, radius, max_queries,
                        isolated)


def _noise_share(events: _Sorted, t: np.ndarray, width: int, height: int, window_us: int, radius: int,
                 max_queries: int | None, isolated: np.ndarray | None) -> float:
    """:func:`noise_share` of the sorted ``events`` (:func:`_sorted_events` with this ``window_us``), their times
    ``t`` (N,) int64 [µs] in the given order, at least two of them apart."""
    from scipy.special import lambertw

    duration_s = (int(t.max()) - int(t.min())) * 1e-6
    area_s = width * height * duration_s                                    # px s

    span_s = float(np.mean(np.minimum(t + window_us, t.max()) - np.maximum(t - window_us, t.min()))) * 1e-6
    near, far = (2 * radius + 1) ** 2 * span_s, (2 * radius + 3) ** 2 * span_s    # px s: cut by the window's ends
    n = events.keys.size
    if isolated is not None:
        if np.shape(isolated) != (n,):
            raise ValueError(f"isolated must hold one flag per event, shape ({n},), got {np.shape(isolated)}")
        tested, scale = np.flatnonzero(np.asarray(isolated, bool)[events.order]), 1.0
    else:
        tested = np.arange(n)
        if max_queries is not None and n > max_queries:
            tested = np.sort(np.random.default_rng(0).choice(n, max_queries, replace=False))
        scale = n / tested.size                                              # N over the tested events
        tested = tested[_alone(events, tested, width, height, window_us, radius)]
    m = tested.size * scale / area_s
    if m * near >= math.exp(-1):
        rate = 1.0 / near
    else:
        low, high = (float(-lambertw(-m * near, k).real) / near for k in (0, -1))
        far_alone = _alone(events, tested, width, height, window_us,
                           radius + 1)                    # alone in the wider square: alone in the narrow one too
        m_far = max(np.count_nonzero(far_alone) * scale, 1) / area_s
        rate = min((low, high), key=lambda r: abs(math.log(max(r * math.exp(-r * far), 1e-300) / m_far)))
    return float(min(1.0, rate * width * height * duration_s / t.size))


def _isolated_noise_share_and_sorted(x: np.ndarray, y: np.ndarray, t: np.ndarray, width: int, height: int,
                                     window_us: int) -> tuple[np.ndarray, float, _Sorted]:
    """:func:`isolated_events` (N,) bool and :func:`noise_share` (radius 1) of the events ``x, y, t`` (N,) [px, px,
    µs], the share from those flags (every event's, as ``noise_share(..., isolated=)``: no subset of queries), and
    the events sorted for both (:func:`_sorted_events` with this ``window_us``), which :func:`_neighbour_counts`
    takes: the fit's depth mask, its noise verdict and its neighbour filter, the events sorted once for all."""
    events = _sorted_events(x, y, t, width, window_us)
    isolated = _isolated(events, width, height, window_us, 1)
    t = np.asarray(t, np.int64)
    if t.size < 2 or t[-1] == t[0]:
        return isolated, 0.0, events
    return isolated, _noise_share(events, t, width, height, window_us, 1, None, isolated), events


def noise_reason(share: float, max_noise_share: float, window_us: int) -> str:
    """The reason of a window whose events are too much background-activity noise to vouch for its depth and
    motion ("" when ``share`` (:func:`noise_share`) is not over ``max_noise_share``); ``window_us`` [µs]: the
    isolated-event test's window, named in the reason.

    >>> noise_reason(0.5, 0.3, 10_000)[:72]
    'about 50% of the events are background-activity noise (isolated events: '
    >>> noise_reason(0.1, 0.3, 10_000)
    ''
    """
    if not share > max_noise_share:
        return ""
    return (f"about {share:.0%} of the events are background-activity noise (isolated events: none other within "
            f"1 px and {window_us / 1000:g} ms; max_noise_share={max_noise_share:g}): the noise's depth cells and "
            "pixels are fitted as if they were the scene's; leave the isolated events out before fitting "
            "(cmax.fitting.quality.isolated_events) or lower the sensor's background activity (its biases, more "
            "light)")


def min_ok_parallax(min_ok_parallax_px: float, width: int, height: int, reference_area: int) -> float:
    """The least parallax [px] of an ``ok`` window with the rotation free on a ``width`` x ``height`` image:
    ``min_ok_parallax_px`` on an image of ``reference_area`` pixels or more, ``sqrt(reference_area / (width
    height))`` times it on a smaller one (never less than ``min_ok_parallax_px``).

    On a smaller image the contrast's optimum itself lies off the truth more often: the same scenes at 160x120
    and 96x72 score the true motion worse than the fit beyond the test's noise on about half and four fifths of
    their windows, at 346x260 on none (docs/quality.md), so a few pixels of parallax that vouch for the
    direction at 346x260 do not on a quarter of the pixels. On a larger image it stays ``min_ok_parallax_px``: with
    the default subsample grown with the sensor (:func:`cmax.fitting.settings.max_events_for`) no ``ok`` window at
    640x480 or 1280x720 was far off, and a threshold grown with the sensor's side flagged right ones
    (docs/quality.md).

    >>> min_ok_parallax(3.0, 346, 260, 346 * 260)
    3.0
    >>> round(min_ok_parallax(3.0, 173, 130, 346 * 260), 6)     # a quarter of the pixels: twice the parallax
    6.0
    >>> min_ok_parallax(3.0, 1280, 720, 346 * 260)              # a larger image: unchanged
    3.0
    """
    area = int(width) * int(height)
    if area <= 0:
        raise ValueError(f"the image must have pixels, got {width}x{height}")
    return float(min_ok_parallax_px) * math.sqrt(max(1.0, reference_area / area))


def small_parallax_reason(parallax_px: float | None, min_ok_parallax_px: float,
                          image_size: tuple[int, int] | None = None, reference_area: int = 346 * 260) -> str:
    """The reason of a window whose translation moved the events too little to vouch for its direction with the
    rotation free, "" otherwise (``parallax_px`` None, or not under the threshold). The threshold is
    ``min_ok_parallax_px``, scaled to an ``image_size`` ``(width, height)`` smaller than ``reference_area``
    pixels by :func:`min_ok_parallax` (None: not scaled).

    Over ``P`` px of parallax, turning the translation direction by an angle ``a`` changes the translational
    image motion by about ``P a`` px, and a rotation takes up its part that is nearly uniform over the image (the
    bas-relief ambiguity of short baselines): what remains is a fraction of a pixel for tens of degrees when
    ``P`` is a few pixels, less than the contrast's own blur, so the fit's direction can be far off while no
    alternative scores within its noise.

    >>> small_parallax_reason(2.0, 3.0)[:62]
    'parallax 2.00 px, under min_ok_parallax_px=3: too little for t'
    >>> small_parallax_reason(4.0, 3.0)
    ''
    >>> small_parallax_reason(4.75, 3.0, (160, 120))[:90]
    'parallax 4.75 px, under 6.49 px (min_ok_parallax_px=3 scaled to a 160x120 image of 19,200 '
    """
    threshold, scaled = min_ok_parallax_px, ""
    if image_size is not None:
        threshold = min_ok_parallax(min_ok_parallax_px, image_size[0], image_size[1], reference_area)
        if threshold > min_ok_parallax_px:
            scaled = (f"{threshold:.2f} px (min_ok_parallax_px={min_ok_parallax_px:g} scaled to a "
                      f"{image_size[0]}x{image_size[1]} image of {image_size[0] * image_size[1]:,} pixels by the square "
                      f"root of min_ok_parallax_area={reference_area:,} over them)")
    if parallax_px is None or not parallax_px < threshold:
        return ""
    under = scaled or f"min_ok_parallax_px={min_ok_parallax_px:g}"
    return (f"parallax {parallax_px:.2f} px, under {under}: too little for the "
            "contrast to tell the translation direction from a rotation (the bas-relief ambiguity)")


def bound_reason(shares: dict[str, float], depth_range: tuple[float, float], max_bound_share: float) -> str:
    """The reason of a window with too much of its depth on an end of ``depth_range`` (near, far) [m], "" otherwise:
    ``shares`` as :func:`cmax.fitting.pipeline.depth_on_bounds` gives them (``{"depth_near": ..., "depth_far":
    ...}``, shares of the events' depth), at least ``max_bound_share`` on one end.

    >>> bound_reason({"depth_near": 0.0, "depth_far": 0.48}, (0.5, 60.0), 0.25)[:61]
    "48% of the events' depth on the far end (60 m) of depth_range"
    >>> bound_reason({"depth_near": 0.1, "depth_far": 0.0}, (0.5, 60.0), 0.25)
    ''
    """
    name, share = max(shares.items(), key=lambda item: item[1])
    if share < max_bound_share:
        return ""
    end = "near" if name == "depth_near" else "far"
    metres = depth_range[0] if end == "near" else depth_range[1]
    beyond = "nearer" if end == "near" else "farther"
    return (f"{share:.0%} of the events' depth on the {end} end ({metres:g} m) of depth_range (at least "
            f"max_bound_share={max_bound_share:g}): the depth is clipped there and the motion may be bent to keep "
            f"the rest inside; the scene may lie {beyond} (widen depth_range) or the speed be in other units")


# ----------------------------------------------------------------------------------------------
# The verdict
# ----------------------------------------------------------------------------------------------
def verdict_of(*, success: bool, failed_stages: Sequence[str], low_motion: LowMotion | None,
               alternatives: Sequence[Alternative], note: str = "", untestable: bool = False,
               rate: float | None = None, max_rate_change: float = math.inf, sparse: str = "",
               on_bound: str = "", small_parallax: str = "", noisy: str = "",
               noise_share: float | None = None, turned: str = "", flat_valley: str = "") -> Quality:
    """The verdict from the fit's ``success`` (and the names of its failed stages), why its motion is too
    small to trust (None when it is not), the ambiguity test's ``alternatives`` and the window's
    :func:`rate_change` ``rate`` (None: not measured); the worst one wins (failed, low parallax, ambiguous,
    ok). ``untestable``: the ambiguity test was due but the window could not hold it (:func:`assess`'s
    ``tested`` False): ambiguous, since nothing tells the fitted direction from its mirror. A ``rate`` over
    ``max_rate_change``: ambiguous and ``unsteady``, the motion is not steady over the window. ``sparse``: the
    :func:`sparse_reason` of the window ("" when it is not sparse): an ``ok`` becomes ambiguous and ``sparse``.
    ``on_bound``: why too much of the depth lies on an end of the depth range (:func:`bound_reason`; "" when it
    does not): an ``ok`` or ambiguous window is ambiguous and ``on_bound``. ``small_parallax``: the
    :func:`small_parallax_reason` of the window ("" when it has parallax enough): an ``ok`` becomes ambiguous and
    ``small_parallax``. ``noisy``: the :func:`noise_reason` of the window ("" when its estimated noise share,
    ``noise_share`` (None: not measured), is not too high): an ``ok`` becomes ambiguous and ``noisy``. ``turned``: the
    :func:`turned_reason` of the window ("" when no motion along the bas-relief trade scores better than the fit):
    an ``ok`` becomes ambiguous and ``turned``. ``flat_valley``: the :func:`valley_reason` of the window ("" when every
    motion ``bas_relief_valley_deg`` along the trade scores worse than the fit beyond noise): an ``ok`` becomes
    ambiguous and ``flat_valley``."""
    unsteady = "" if rate is None else _unsteady_reason(rate, max_rate_change)
    measured = dict(rate_change=rate, unsteady=bool(unsteady), noise_share=noise_share)
    if not success:
        return Quality(Verdict.FAILED, f"stage(s) failed: {', '.join(failed_stages) or 'unknown'}",
                       tuple(alternatives), **measured)
    if low_motion is not None:
        return Quality(Verdict.LOW_PARALLAX, low_motion.reason, tuple(alternatives), cause=low_motion.cause,
                       **measured)
    close = [a for a in alternatives if a.within_noise]
    if close:
        verdict = Verdict.AMBIGUOUS
        reason = "; ".join(f"{a.name} within noise (gain {a.gain:.3g} <= noise {a.noise:.3g})" if a.gain >= -a.noise
                           else f"{a.name} scores better beyond noise (gain {a.gain:.3g} < -noise {a.noise:.3g}: the "
                                "fit missed it)" for a in close)
    elif untestable:
        verdict = Verdict.AMBIGUOUS
        reason = (f"{note or 'ambiguity not tested'}: nothing tells the fitted direction from its mirrored or "
                  "rotation-swapped alternatives")
    elif alternatives:
        verdict, worst = Verdict.OK, min(alternatives, key=lambda a: a.gain)
        reason = (f"every alternative scores worse beyond noise (closest: {worst.name}, gain {worst.gain:.3g} > "
                  f"noise {worst.noise:.3g})" + (f"; {note}" if note else ""))
    else:
        verdict, reason = Verdict.OK, note or "no alternative tested"
    if unsteady:
        verdict, reason = Verdict.AMBIGUOUS, f"{unsteady}; {reason}"
    if on_bound:
        verdict, reason = Verdict.AMBIGUOUS, f"{on_bound}; {reason}"
        measured["on_bound"] = True
    if sparse and verdict is Verdict.OK:
        return Quality(Verdict.AMBIGUOUS, f"{sparse}; {reason}", tuple(alternatives), sparse=True, **measured)
    if small_parallax and verdict is Verdict.OK:
        return Quality(Verdict.AMBIGUOUS, f"{small_parallax}; {reason}", tuple(alternatives), small_parallax=True,
                       **measured)
    if noisy and verdict is Verdict.OK:
        return Quality(Verdict.AMBIGUOUS, f"{noisy}; {reason}", tuple(alternatives), noisy=True, **measured)
    if turned and verdict is Verdict.OK:
        return Quality(Verdict.AMBIGUOUS, f"{turned}; {reason}", tuple(alternatives), turned=True, **measured)
    if flat_valley and verdict is Verdict.OK:
        return Quality(Verdict.AMBIGUOUS, f"{flat_valley}; {reason}", tuple(alternatives), flat_valley=True,
                       **measured)
    return Quality(verdict, reason, tuple(alternatives), **measured)


# ----------------------------------------------------------------------------------------------
# Resolution from neighbours
# ----------------------------------------------------------------------------------------------
def _distance_deg(v: np.ndarray, omega: np.ndarray, v_ref: np.ndarray, omega_ref: np.ndarray,
                  duration_s: float) -> float:
    """Angle between the directions of ``v`` and ``v_ref`` [deg] plus the rotation between ``omega`` and
    ``omega_ref`` accumulated over the window [deg]."""
    cos = float(np.dot(v, v_ref) / max(np.linalg.norm(v) * np.linalg.norm(v_ref), 1e-12))
    angle = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    return angle + math.degrees(float(np.linalg.norm(np.asarray(omega) - omega_ref)) * duration_s)


#: The resolution of an ambiguous window that no confident neighbour can resolve.
NO_CONFIDENT_NEIGHBOUR = "unresolved: no confident (ok) neighbour window"


class _Candidate(NamedTuple):
    """A motion an ambiguous window may take: its fit (``alternative`` None) or an alternative within noise;
    ``score`` is 0 for the fit and minus the alternative's gain (above 0: it scored better than the fit)."""

    name: str
    alternative: "Alternative | None"
    v: np.ndarray
    omega: np.ndarray
    score: float


def _candidates(v: np.ndarray, omega: np.ndarray, quality: Quality) -> list[_Candidate]:
    """The fit ``(v, omega)`` and the alternatives of ``quality`` within noise, as :class:`_Candidate`."""
    return [_Candidate("fit", None, np.asarray(v, float), np.asarray(omega, float), 0.0)] + [
        _Candidate(a.name, a, a.v, a.omega, -a.gain) for a in quality.alternatives if a.within_noise]


def choose_from_neighbours(v: np.ndarray, omega: np.ndarray, quality: Quality,
                           neighbours: Sequence[tuple[np.ndarray, np.ndarray]], duration_s: float,
                           max_resolve_deg: float) -> tuple[Alternative | None, Quality]:
    """Resolve an ambiguous window from its confident neighbours' ``(v, omega)`` motions.

    The candidates are the fit ``(v, omega)`` and its alternatives within noise; the one closest to the
    neighbours' mean motion (:func:`_distance_deg`: direction angle plus rotation over the window) wins
    when closer than ``max_resolve_deg``. Returns the chosen alternative (None: keep the fit, or
    unresolved) and the quality with ``resolution``/``resolved`` filled in.
    """
    if quality.verdict is not Verdict.AMBIGUOUS:
        return None, quality
    if not neighbours:
        return None, _with(quality, NO_CONFIDENT_NEIGHBOUR, False)
    units = [np.asarray(nv, float) / max(np.linalg.norm(nv), 1e-12) for nv, _ in neighbours]
    v_ref = np.mean(units, 0)
    omega_ref = np.mean([np.asarray(no, float) for _, no in neighbours], 0)
    distance, name, alt = min(((_distance_deg(c.v, c.omega, v_ref, omega_ref, duration_s), c.name, c.alternative)
                               for c in _candidates(v, omega, quality)), key=lambda s: s[0])
    if distance > max_resolve_deg:
        return None, _with(quality, f"unresolved: the closest candidate ({name}) is {distance:.0f} deg from the "
                                    f"{len(neighbours)} neighbour(s), over {max_resolve_deg:g}", False)
    if alt is None:
        return None, _with(quality, f"resolved: kept the fit, closest to the {len(neighbours)} neighbour(s) "
                                    f"({distance:.0f} deg)", True)
    return alt, _with(quality, f"resolved: took the {name} alternative, within noise and closest to the "
                               f"{len(neighbours)} neighbour(s) ({distance:.0f} deg)", True)


def choose_from_run(motions: Sequence[tuple[np.ndarray, np.ndarray]], qualities: Sequence[Quality],
                    durations_s: Sequence[float], max_resolve_deg: float
                    ) -> list[tuple[Alternative | None, Quality]]:
    """Resolve a run of consecutive ambiguous windows that has no confident neighbour by the run's pooled
    evidence, assuming one motion for the run (the motion prior of a sequence, with nothing to anchor it).

    Each window ``i`` has candidates: its fit ``motions[i] = (v, omega)`` (score 0) and its alternatives
    within noise (score ``-gain``: above 0 when the alternative scored better than the fit on the window's
    own objective). A hypothesis is a candidate of some window that every window of the run has a candidate
    near (:func:`_distance_deg` within ``max_resolve_deg``); its evidence ``E`` is the sum over the windows of
    their best-scoring candidate near it. The hypothesis of the highest evidence wins when it is above that of
    every hypothesis farther than ``max_resolve_deg`` from it by more than the run's pooled noise,
    ``sqrt(sum_i noise_i^2)`` (``noise_i``: the largest noise of window ``i``'s alternatives), and each window
    takes its candidate near it; otherwise the whole run stays unresolved, and says why. A run of one window
    cannot gain on its own noise: it stays unresolved; so does a run whose winner has no rival only because some
    of its windows have no alternative within noise (ambiguous as sparse or untested): they hold their fit alone,
    so no rival can cover them, and neighbours fitted one from the other agree by construction.

    Returns, per window, the chosen alternative (None: keep the fit, or unresolved) and the quality with
    ``resolution``/``resolved`` filled in.
    """
    count = len(motions)
    if count < 2 or any(q.verdict is not Verdict.AMBIGUOUS for q in qualities):
        return [(None, _with(q, NO_CONFIDENT_NEIGHBOUR, False)) for q in qualities]
    candidates = [_candidates(v, omega, q) for (v, omega), q in zip(motions, qualities)]

    def support(hypothesis: _Candidate) -> tuple[list[_Candidate | None], float]:
        """Each window's best-scoring candidate near ``hypothesis`` (None when it has none), and the evidence:
        their summed scores, -inf unless every window has one."""
        picks = []
        for window, duration in zip(candidates, durations_s):
            near = [c for c in window
                    if _distance_deg(c.v, c.omega, hypothesis.v, hypothesis.omega, duration) <= max_resolve_deg]
            picks.append(max(near, key=lambda c: c.score) if near else None)
        return picks, (sum(c.score for c in picks) if all(c is not None for c in picks) else -math.inf)

    covered = [(h, *support(h)) for window in candidates for h in window]
    covered = [(h, picks, evidence) for h, picks, evidence in covered if math.isfinite(evidence)]
    noise = math.sqrt(sum(max((a.noise for a in q.alternatives), default=0.0) ** 2 for q in qualities))
    if not covered:
        return [(None, _with(q, f"{NO_CONFIDENT_NEIGHBOUR}; no one motion has a candidate in each of the run's "
                                f"{count} ambiguous windows", False)) for q in qualities]
    best, picks, evidence = max(covered, key=lambda entry: entry[2])
    duration = float(np.median(durations_s))
    rival = max((e for h, _, e in covered
                 if _distance_deg(h.v, h.omega, best.v, best.omega, duration) > max_resolve_deg), default=-math.inf)
    unweighed = sum(len(window) == 1 for window in candidates)
    if not math.isfinite(rival) and unweighed:
        # No other motion covers the run only because some windows hold their fit alone: no alternative within
        # noise (each is ambiguous for another reason: too few events per pixel, too few patches to test), so
        # they support no rival, and warm-started neighbours agree with each other by construction.
        some = ("none of them has an" if unweighed == count
                else f"{unweighed} of them {'has' if unweighed == 1 else 'have'} no")
        return [(None, _with(q, f"{NO_CONFIDENT_NEIGHBOUR}; no other motion has a candidate in each of the run's "
                                f"{count} ambiguous windows, but {some} alternative within noise to weigh "
                                "their fit against, and neighbours fitted one from the other agreeing is no "
                                "evidence", False)) for q in qualities]
    if not evidence - rival > noise:
        return [(None, _with(q, f"{NO_CONFIDENT_NEIGHBOUR}; pooled over the run of {count} ambiguous windows the "
                                f"best motion's evidence {evidence:.3g} is within the pooled noise {noise:.3g} of "
                                f"another's ({rival:.3g})", False)) for q in qualities]
    why = (f"it is the only motion with a candidate in every window (pooled noise {noise:.3g})" if not math.isfinite(rival)
           else f"its evidence {evidence:.3g} beats the other motion's {rival:.3g} by more than the pooled noise "
                f"{noise:.3g}")
    out = []
    for pick, q in zip(picks, qualities):
        what = "kept the fit" if pick.alternative is None else f"took the {pick.name} alternative"
        out.append((pick.alternative, _with(q, f"resolved: {what}, no confident neighbour; pooled over the run of "
                                               f"{count} ambiguous windows one motion wins: {why}", True)))
    return out


def _with(quality: Quality, resolution: str, resolved: bool) -> Quality:
    return replace(quality, resolution=resolution, resolved=resolved)
