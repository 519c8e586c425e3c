"""Solver backends of :func:`cmax.fit`: small strategy objects around one :class:`Problem`.

A :class:`Problem` is a smooth function of a parameter vector with its
gradient (from torch autograd), box bounds, and optionally the scale
constraint ``|x[v]| = speed`` on a slice ``v`` of the parameters. Backends:

* :class:`ScipySolver` — L-BFGS-B with bounds (scipy). It cannot take equality
  constraints, so the driver parameterises ``v = speed * u / |u|`` for it
  (:attr:`Solver.takes_equality` is False).
* :class:`CasadiSolver` — IPOPT with a limited-memory Hessian (casadi), the
  scale as the equality constraint ``|v|^2 = speed^2``; the objective and its
  gradient enter as casadi callbacks.
* :class:`TorchSolver` — Adam steps with projection onto the bounds (torch), a
  baseline and the optimizer the learned package uses.

Every backend returns a :class:`SolveResult`. :func:`solve` is the one entry point of the fit's
stages: it turns a torch loss into a :class:`Problem`, runs the backend with the stage's iteration
limit and tolerances, and never hands back a point scoring worse than the start (it keeps the start
and says so in the message, with ``success`` False).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["Problem", "SolveResult", "Solver", "ScipySolver", "CasadiSolver", "TorchSolver", "Tolerances",
           "GradientLoss", "make_solver", "solve", "torch_fun_and_grad"]


@dataclass(frozen=True)
class Tolerances:
    """Stopping tolerances of one solve: ``ftol`` relative decrease of the objective, ``gtol`` largest
    projected gradient component (L-BFGS-B's names; IPOPT takes ``gtol`` as its ``tol``; Adam runs its
    iterations)."""

    ftol: float = 1e-7
    gtol: float = 1e-6

    def __post_init__(self) -> None:
        if not (self.ftol > 0 and self.gtol > 0):
            raise ValueError(f"tolerances must be positive, got ftol={self.ftol}, gtol={self.gtol}")


#: scipy.optimize.minimize's own L-BFGS-B defaults (the refinement's tolerances; the patch flows' gtol).
SCIPY_DEFAULT_TOLERANCES = Tolerances(ftol=2.220446049250313e-09, gtol=1e-05)
#: Looser tolerances for a 2-parameter flow: its error is below 0.1 px well before the default stops.
RELAXED_TOLERANCES = Tolerances(ftol=1e-5, gtol=1e-4)


@dataclass(frozen=True, eq=False)
class Problem:
    """Minimise ``fun_and_grad(x) -> (f, df/dx)`` over ``lower <= x <= upper``.

    ``speed`` with ``v_slice`` asks for ``|x[v_slice]| = speed`` (solvers with
    :attr:`Solver.takes_equality`); ``x0`` must satisfy the bounds.
    """

    fun_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]]
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    speed: float | None = None
    v_slice: slice | None = None

    @property
    def constrained(self) -> bool:
        """Whether the problem asks for ``|x[v_slice]| = speed``."""
        return self.speed is not None and self.v_slice is not None


@dataclass(frozen=True)
class SolveResult:
    """One solve: the point ``x``, its objective ``fun``, the counts, the backend's message and whether it
    succeeded; ``fun_start`` is the objective at the start, ``kept_start`` whether :func:`solve` handed back
    the start because the backend ended worse (or not finite)."""

    x: np.ndarray
    fun: float
    iterations: int
    evaluations: int
    message: str
    success: bool
    seconds: float
    fun_start: float = float("nan")
    kept_start: bool = False


class _Counted:
    """Caches the last evaluation (IPOPT asks for f and grad separately) and counts calls."""

    def __init__(self, fun_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]],
                 feasible: Callable[[np.ndarray], bool] | None = None) -> None:
        self.fun_and_grad, self.calls, self._x, self._value = fun_and_grad, 0, None, None
        self.feasible, self.best_x, self.best_f = feasible, None, np.inf

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        x = np.asarray(x, dtype=np.float64).ravel()
        if self._x is None or not np.array_equal(x, self._x):
            self.calls += 1
            f, g = self.fun_and_grad(x)
            self._x, self._value = x.copy(), (float(f), np.asarray(g, dtype=np.float64).ravel())
            if self.feasible is not None and self._value[0] < self.best_f and self.feasible(x):
                self.best_x, self.best_f = x.copy(), self._value[0]
        return self._value


class Solver:
    """Base of the backends: ``solve(problem) -> SolveResult``."""

    takes_equality = False
    max_iterations: int = 100

    def solve(self, problem: Problem) -> SolveResult:  # pragma: no cover - interface
        """Minimise ``problem`` (its ``fun_and_grad`` from ``x0`` within its bounds, with ``|v| = speed``
        where it asks and the backend takes equalities); the best point and what the backend said."""
        raise NotImplementedError

    def with_iterations(self, n: int) -> "Solver":
        """A copy limited to ``n`` iterations."""
        copy = type(self).__new__(type(self))
        copy.__dict__.update(self.__dict__)
        copy.max_iterations = int(n)
        return copy

    def with_tolerances(self, tolerances: Tolerances | None) -> "Solver":
        """A copy with these stopping tolerances (None: the backend's own); backends without
        tolerances return themselves."""
        return self


class ScipySolver(Solver):
    """L-BFGS-B (scipy.optimize.minimize) with torch gradients.

    Tolerances are set for a normalised objective (about -1 at the start) and
    parameters in pixels of displacement: ``ftol`` relative decrease,
    ``gtol`` projected gradient.
    """

    def __init__(self, *, max_iterations: int = 100, ftol: float = 1e-7, gtol: float = 1e-6, memory: int = 10) -> None:
        self.max_iterations, self.ftol, self.gtol, self.memory = max_iterations, ftol, gtol, memory

    def with_tolerances(self, tolerances: Tolerances | None) -> "ScipySolver":
        if tolerances is None:
            return self
        copy = self.with_iterations(self.max_iterations)
        copy.ftol, copy.gtol = tolerances.ftol, tolerances.gtol
        return copy

    def solve(self, problem: Problem) -> SolveResult:
        from scipy.optimize import minimize

        start = time.perf_counter()
        f = _Counted(problem.fun_and_grad)
        result = minimize(f, problem.x0, jac=True, method="L-BFGS-B",
                          bounds=list(zip(problem.lower, problem.upper)),
                          options={"maxiter": self.max_iterations, "ftol": self.ftol, "gtol": self.gtol,
                                   "maxcor": self.memory})
        return SolveResult(np.asarray(result.x), float(result.fun), int(result.nit), f.calls,
                           str(result.message), bool(result.success), time.perf_counter() - start)


class TorchSolver(Solver):
    """Adam on the parameter vector with projection onto the bounds; step ``lr`` in parameter units."""

    def __init__(self, *, max_iterations: int = 100, lr: float = 0.3) -> None:
        self.max_iterations, self.lr = max_iterations, lr

    def solve(self, problem: Problem) -> SolveResult:
        import torch

        start = time.perf_counter()
        f = _Counted(problem.fun_and_grad)
        x = torch.tensor(problem.x0, dtype=torch.float64, requires_grad=True)
        optimizer = torch.optim.Adam([x], lr=self.lr)
        lower, upper = torch.from_numpy(problem.lower), torch.from_numpy(problem.upper)
        best_x, best_f = problem.x0.copy(), f(problem.x0)[0]
        for _ in range(self.max_iterations):
            value, grad = f(x.detach().numpy())
            if value < best_f:
                best_x, best_f = x.detach().numpy().copy(), value
            optimizer.zero_grad()
            x.grad = torch.from_numpy(grad)
            optimizer.step()
            with torch.no_grad():
                x.copy_(torch.maximum(torch.minimum(x, upper), lower))
        value, _ = f(x.detach().numpy())
        if value < best_f:
            best_x, best_f = x.detach().numpy().copy(), value
        return SolveResult(best_x, float(best_f), self.max_iterations, f.calls,
                           f"Adam: {self.max_iterations} steps", True, time.perf_counter() - start)


class CasadiSolver(Solver):
    """IPOPT (casadi) with a limited-memory Hessian; the scale as an equality constraint on |v|.

    IPOPT starts from the given point moved at most ``bound_push`` (relative) away from the bounds
    (its own default, 1e-2, can move a good start by enough to lose the contrast it had). Its iterates
    need not improve the objective monotonically (its filter line search trades the objective against
    the constraint), so at its iteration limit its last point can score worse than an earlier one, or lie
    off the constraint.
    The solver therefore returns a point on ``|v| = speed`` (its last point moved there and evaluated
    again when it is not), or the best point IPOPT evaluated whose ``|v|`` is within ``feasibility``
    (relative) of the speed, moved onto ``|v| = speed`` and evaluated there, when that scores better than
    both the last point and the start (the message says which; ``success`` stays IPOPT's own).
    """

    takes_equality = True

    def __init__(self, *, max_iterations: int = 100, tol: float = 1e-6, feasibility: float = 1e-3,
                 bound_push: float = 1e-8) -> None:
        if not (feasibility > 0 and bound_push > 0):
            raise ValueError(f"feasibility and bound_push must be positive, got {feasibility}, {bound_push}")
        self.max_iterations, self.tol, self.feasibility, self.bound_push = max_iterations, tol, feasibility, bound_push

    def _feasible(self, problem: Problem) -> Callable[[np.ndarray], bool]:
        """Whether a point lies within the bounds (IPOPT relaxes them by about 1e-8) and, with the scale
        constraint, has ``|v|`` within :attr:`feasibility` of the speed."""
        span = np.maximum(np.abs(problem.lower), np.abs(problem.upper))
        slack = 1e-7 * np.where(np.isfinite(span), np.maximum(span, 1.0), 1.0)

        def feasible(x: np.ndarray) -> bool:
            if np.any(x < problem.lower - slack) or np.any(x > problem.upper + slack):
                return False
            if not problem.constrained:
                return True
            return abs(np.linalg.norm(x[problem.v_slice]) - problem.speed) <= self.feasibility * problem.speed

        return feasible

    def _on_constraint(self, problem: Problem, x: np.ndarray) -> np.ndarray:
        """``x`` inside the bounds with ``|v| = speed`` exactly (when the problem has the constraint)."""
        x = np.clip(x, problem.lower, problem.upper)
        if problem.constrained:
            v = x[problem.v_slice]
            x[problem.v_slice] = v * (problem.speed / max(np.linalg.norm(v), 1e-300))
        return x

    def solve(self, problem: Problem) -> SolveResult:
        import casadi as ca

        start = time.perf_counter()
        f = _Counted(problem.fun_and_grad, self._feasible(problem))
        n = len(problem.x0)
        objective = _objective_callback(ca, f, n)
        X = ca.MX.sym("x", n)
        nlp = {"x": X, "f": objective(X)}
        lbg = ubg = None
        if problem.constrained:
            v = X[problem.v_slice.start:problem.v_slice.stop]
            nlp["g"] = ca.sumsqr(v) - problem.speed ** 2
            lbg = ubg = 0.0
        options = {"ipopt.hessian_approximation": "limited-memory", "ipopt.max_iter": self.max_iterations,
                   "ipopt.tol": self.tol, "ipopt.print_level": 0, "print_time": False,
                   "ipopt.sb": "yes", "ipopt.bound_push": self.bound_push, "ipopt.bound_frac": self.bound_push}
        solver = ca.nlpsol("cmax_fit", "ipopt", nlp, options)
        arguments = {"x0": problem.x0, "lbx": problem.lower, "ubx": problem.upper}
        if lbg is not None:
            arguments.update(lbg=lbg, ubg=ubg)
        solution = solver(**arguments)
        stats = solver.stats()
        x, value = np.asarray(solution["x"]).ravel(), float(solution["f"])
        message = str(stats.get("return_status", ""))
        moved = self._on_constraint(problem, x.copy())
        if not np.array_equal(moved, x):                            # off the constraint (or the bounds)
            moved_value = f(moved)[0]
            if not np.allclose(moved, x, rtol=1e-6, atol=1e-9):     # more than IPOPT's own tolerance
                message += (f"; its last point, off the constraint, moved onto |v| = speed (objective "
                            f"{value:.6g} -> {moved_value:.6g})")
            x, value = moved, moved_value
        if f.best_x is not None and f.best_f < value and f.best_f < (f0 := f(problem.x0)[0]):
            best = self._on_constraint(problem, f.best_x.copy())
            best_value = f(best)[0]
            if best_value < min(value, f0):
                message += f"; returned its best evaluated point ({best_value:.6g} < its last {value:.6g})"
                x, value = best, best_value
        return SolveResult(x, value, int(stats.get("iter_count", 0)), f.calls, message,
                           bool(stats.get("success", False)), time.perf_counter() - start)

    def with_tolerances(self, tolerances: Tolerances | None) -> "CasadiSolver":
        if tolerances is None:
            return self
        copy = self.with_iterations(self.max_iterations)
        copy.tol = tolerances.gtol
        return copy


def _objective_callback(ca, f: _Counted, n: int):
    """A casadi function of x (n,) with a callback gradient (the object is kept alive on the result)."""

    class Gradient(ca.Callback):
        def __init__(self, name, opts=None):
            ca.Callback.__init__(self)
            self.construct(name, opts or {})

        def get_n_in(self): return 2
        def get_n_out(self): return 1

        def get_sparsity_in(self, i):
            return ca.Sparsity.dense(n, 1) if i == 0 else ca.Sparsity.dense(1, 1)

        def get_sparsity_out(self, i):
            return ca.Sparsity.dense(1, n)

        def eval(self, arg):
            return [ca.DM(f(np.asarray(arg[0]).ravel())[1]).T]

    class Objective(ca.Callback):
        def __init__(self, name, opts=None):
            ca.Callback.__init__(self)
            self.construct(name, opts or {})

        def get_n_in(self): return 1
        def get_n_out(self): return 1
        def get_sparsity_in(self, i): return ca.Sparsity.dense(n, 1)
        def get_sparsity_out(self, i): return ca.Sparsity.dense(1, 1)

        def eval(self, arg):
            return [f(np.asarray(arg[0]).ravel())[0]]

        def has_jacobian(self): return True

        def get_jacobian(self, name, inames, onames, opts):
            self._gradient = Gradient(name, opts)
            return self._gradient

    return Objective("cmax_objective")


def make_solver(solver: "str | Solver") -> Solver:
    """A backend from its name (``"scipy"``, ``"casadi"``, ``"torch"``) or an instance (returned as is)."""
    if isinstance(solver, Solver):
        return solver
    table = {"scipy": ScipySolver, "casadi": CasadiSolver, "torch": TorchSolver}
    if solver not in table:
        raise ValueError(f"solver must be one of {sorted(table)} or a cmax.fitting.solvers.Solver, got {solver!r}")
    return table[solver]()


def torch_fun_and_grad(loss: Callable) -> Callable[[np.ndarray], tuple[float, np.ndarray]]:
    """``x (n,) float64 -> (loss, d loss / dx (n,))`` of a torch ``loss(params (n,) float64 tensor) -> scalar``."""
    import torch

    def fun_and_grad(x: np.ndarray) -> tuple[float, np.ndarray]:
        p = torch.tensor(x, dtype=torch.float64, requires_grad=True)
        value = loss(p)
        (grad,) = torch.autograd.grad(value, p)
        return float(value.detach()), grad.numpy().copy()

    return fun_and_grad


@dataclass(frozen=True)
class GradientLoss:
    """A loss given by its value and gradient, ``fun_and_grad(x (n,) float64) -> (float, (n,) float64)``, for
    :func:`solve`: objectives that compute their own gradient (compiled kernels) instead of torch autograd."""

    fun_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]]


def solve(loss: "Callable | GradientLoss", x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, solver: Solver, *,
          iterations: int, tolerances: Tolerances | None = None, norm_slice: slice | None = None,
          norm: float = 1.0) -> SolveResult:
    """Minimise ``loss`` over ``lower <= x <= upper`` from ``x0`` (n,): a torch ``loss(params (n,) float64) ->
    scalar`` (differentiated by autograd) or a :class:`GradientLoss`.

    The one solve path of :func:`cmax.fit`: ``solver`` limited to ``iterations`` with ``tolerances``;
    ``norm_slice`` asks backends that take equality constraints (:attr:`Solver.takes_equality`) for
    ``|x[norm_slice]| = norm``. ``x0`` is clipped into the bounds. When the backend ends worse than the
    start (or not finite) the start is returned with ``kept_start`` True and ``success`` False: no solve
    hands back a point scoring worse than its start.
    """
    f = _Counted(loss.fun_and_grad if isinstance(loss, GradientLoss) else torch_fun_and_grad(loss))
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    x0 = np.clip(np.asarray(x0, dtype=np.float64), lower, upper)
    f0 = f(x0)[0]
    problem = Problem(f, x0, lower, upper, speed=norm if norm_slice is not None else None, v_slice=norm_slice)
    result = solver.with_iterations(iterations).with_tolerances(tolerances).solve(problem)
    worse = not np.isfinite(result.fun) or not np.all(np.isfinite(result.x)) or result.fun > f0
    if worse:
        return SolveResult(x0.copy(), f0, result.iterations, result.evaluations + f.calls,
                           f"{result.message}; kept the start (the solver ended at {result.fun:.6g} > {f0:.6g})",
                           False, result.seconds, fun_start=f0, kept_start=True)
    return SolveResult(result.x, result.fun, result.iterations, result.evaluations, result.message,
                       result.success, result.seconds, fun_start=f0)
