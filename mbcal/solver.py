"""Marquardt's method with random restarts, compiled with JAX (seed, section 3.4, eqs. 15–18).

Each iteration solves ``(JᵀJ + λ·D) δ = −Jᵀr`` for the whitened residual r = W^½ (h(x) − y) and
its Jacobian J = W^½ ∂h/∂x, where D is the diagonal of JᵀJ as Marquardt proposed (kept as a
running maximum, as MINPACK does, so a column that vanishes does not make the system singular).
λ adapts to the nonlinearity by the gain ratio (Nielsen's rule). J comes from ``jax.jacfwd``
together with r in one pass; the loop keeps JᵀJ and Jᵀr of the accepted point, not J. A step is
taken when S decreases, or when the predicted and the computed change are both below what float64
resolves in S (then S has converged to working precision). The whole iteration loop is one
``lax.while_loop``; all restarts run
vmapped in one compiled call, a restart that finishes is frozen while the others go on, and a
restart that fails (non-finite residuals) gets its status without stopping the batch.

The low-level entry point :func:`least_squares` solves any residual function, so the solver
serves beyond .mdl models (the NIST StRD tests use it directly).

Two options change the step, and only when asked for (without them the compiled program is the
one it always was, bit for bit):

- **Hard bounds** (``bounds=(lower, upper)``): projected Marquardt steps, as Ceres does for box
  constraints.  At x, an unknown on a bound whose gradient pushes it outwards is *active* and
  held fixed (its row and column of the damped system are replaced by the identity, its
  right-hand side by 0); the others take the Marquardt step δ, and the trial point is
  clip(x + δ, lower, upper), so every iterate is inside.  The gain ratio uses the decrease the
  linear model predicts for the step actually taken, s = clip(x + δ) − x; the gradient test
  uses the projected gradient (0 for active unknowns).  The result says which unknowns end on
  an active bound (:attr:`LeastSquaresResult.active`).
- **A local parameterisation** (``local=...``, :class:`LocalParameterisation`): the solver steps
  in local coordinates d about the current x — the Jacobian is ∂r(x ⊞ d)/∂d at d = 0 and the
  trial point is x ⊞ δ.  :class:`mbcal.problem.Problem` offers one that steps roll-pitch-yaw
  orientations in a rotation vector (no gimbal lock); ``SolverConfig(manifold=False)`` turns
  it off.
"""

from __future__ import annotations

import enum
import functools
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple, Protocol

import numpy as np

from mbcal._jax import as_argument, in_float64, jax, jit, jnp
from mbcal.cache import Hasher, exported
from mbcal.errors import SolverError
from mbcal.staging import StaleRecipeError, forget, prepare

Array = Any

__all__ = [
    "Status",
    "SolverConfig",
    "Loss",
    "LeastSquaresResult",
    "LocalParameterisation",
    "least_squares",
    "random_starts",
    "check_size",
    "solver_byte_limit",
    "MAX_RESTARTS",
    "MAX_DENSE_UNKNOWNS",
    "MAX_SOLVER_BYTES",
]


class Status(enum.IntEnum):
    """How a restart ended. ``converged`` is true for the first three."""

    CONVERGED_COST = 1
    CONVERGED_STEP = 2
    CONVERGED_GRADIENT = 3
    MAX_ITERATIONS = 4
    NON_FINITE = 5
    STALLED = 6

    @property
    def converged(self) -> bool:
        return self in (Status.CONVERGED_COST, Status.CONVERGED_STEP, Status.CONVERGED_GRADIENT)

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @property
    def label(self) -> str:
        return self.name.lower()


_MESSAGES = {
    Status.CONVERGED_COST: "converged: S changed by less than ftol (relative), or by less than float64 resolves",
    Status.CONVERGED_STEP: "converged: the step is smaller than xtol (relative)",
    Status.CONVERGED_GRADIENT: "converged: the gradient is orthogonal to the residuals within gtol",
    Status.MAX_ITERATIONS: "stopped: the iteration limit was reached before convergence",
    Status.NON_FINITE: "failed: the residuals are not finite at the initial values",
    Status.STALLED: "stopped: λ grew past its limit without reducing S (a saddle, a bound of the model, or "
    "numerical noise)",
}


class Loss(enum.StrEnum):
    """Robust loss ρ(s) applied to each squared whitened residual s = r².

    A ``str`` enum: ``SolverConfig(loss="huber")`` and ``SolverConfig(loss=Loss.HUBER)`` are the same.
    """

    LINEAR = "linear"
    HUBER = "huber"
    CAUCHY = "cauchy"

    @property
    def default_scale(self) -> float:
        """The scale c (in σ) that gives 95 % efficiency on Gaussian residuals (Huber 1.345,
        Cauchy 2.385; Holland & Welsch 1977), the default of :class:`SolverConfig` and the CLI."""
        return _DEFAULT_SCALES[self]


_DEFAULT_SCALES = {Loss.LINEAR: 1.0, Loss.HUBER: 1.345, Loss.CAUCHY: 2.385}


@dataclass(frozen=True)
class SolverConfig:
    """Settings of the Marquardt solver.

    The default tolerances (1e-10) stop far below any statistical uncertainty of a calibration
    and save the iterations that only chase round-off; use 1e-15 for reference-grade precision
    (the NIST StRD checks do).

    Attributes
    ----------
    max_iterations : int
        Iteration limit per restart.  A restart that hits it holds up the vmapped batch, so keep
        it modest; raise it for hard problems.
    ftol : float
        Converged when an accepted step changes S by less than ``ftol · S``.
    xtol : float
        Converged when the step is shorter than ``xtol · (‖x‖ + xtol)``.
    gtol : float
        Converged when max_j |J_jᵀ r| / (‖J_j‖ ‖r‖) < gtol (the residual is orthogonal to every
        column of J: MINPACK's scale-free gradient test).
    lambda_init : float
        Initial λ, relative to diag(JᵀJ).
    lambda_max : float
        λ beyond which a restart is declared stalled.
    loss : Loss or str
        ``linear`` (least squares), ``huber`` or ``cauchy``.
    loss_scale : float, optional
        Scale c of the robust loss, in units of the whitened residual (σ): residuals below c
        count quadratically.  Default: :attr:`Loss.default_scale` (Huber 1.345, Cauchy 2.385).
    manifold : bool
        Use the local parameterisation the caller offers (``least_squares(..., local=...)``):
        for a calibration, orientations whose roll, pitch and yaw are all unknown are stepped
        in a rotation vector about the current orientation, so they converge at ±90° pitch
        (gimbal lock) too.  False: plain additive steps in the angles.  Without an offer
        (problems without such orientations) it changes nothing.
    structure : str
        How :func:`mbcal.calibrate` solves a problem whose configurations have unknowns of their
        own (board poses): ``auto`` (the Schur complement of :mod:`mbcal.structured` when it pays,
        see :func:`mbcal.structured.pays`), ``structured`` (always; an error when the problem has
        no such structure) or ``dense`` (the dense solver of this module).  Issue 15.
    """

    max_iterations: int = 100
    ftol: float = 1e-10
    xtol: float = 1e-10
    gtol: float = 1e-10
    lambda_init: float = 1e-3
    lambda_max: float = 1e16
    loss: Loss = Loss.LINEAR
    loss_scale: float | None = None
    manifold: bool = True
    structure: str = "auto"

    def __post_init__(self) -> None:
        if self.structure not in ("auto", "structured", "dense"):
            raise SolverError(f"unknown structure '{self.structure}' (auto, structured or dense)")
        try:
            loss = Loss(self.loss)
        except ValueError:
            raise SolverError(f"unknown loss '{self.loss}' (linear, huber or cauchy)") from None
        # Frozen: normalise the fields once, so equal settings hash equal (the compiled-code cache).
        object.__setattr__(self, "loss", loss)
        scale = loss.default_scale if self.loss_scale is None else self.loss_scale
        object.__setattr__(self, "loss_scale", scale)
        if not scale > 0:
            raise SolverError(f"loss_scale must be positive, got {scale}")
        if self.max_iterations < 1:
            raise SolverError("max_iterations must be at least 1")
        for name in ("ftol", "xtol", "gtol"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):  # a negative one never stops: the loop hits its cap
                raise SolverError(f"{name} must be a finite number ≥ 0, got {value}")
        if not (np.isfinite(self.lambda_init) and self.lambda_init > 0 and self.lambda_max > self.lambda_init):
            raise SolverError(
                f"lambda_init must be positive and below lambda_max, got {self.lambda_init} and {self.lambda_max}"
            )


def robust(loss: Loss | str, scale: float, s: Array) -> tuple[Array, Array]:
    """ρ(s) and ρ'(s) for squared residuals ``s`` (ρ(s) = s for least squares)."""
    c2 = scale * scale
    if loss == "huber":
        root = jnp.sqrt(jnp.where(s > c2, s, c2))
        rho = jnp.where(s <= c2, s, 2.0 * scale * root - c2)
        drho = jnp.where(s <= c2, 1.0, scale / root)
        return rho, drho
    if loss == "cauchy":
        return c2 * jnp.log1p(s / c2), 1.0 / (1.0 + s / c2)
    return s, jnp.ones_like(s)


def robust_system(loss: Loss | str, scale: float, r: Array, J: Array) -> tuple[Array, Array, Array]:
    """The robust cost Σρ(r²) and the reweighted residual and Jacobian √ρ'·r, √ρ'·J (iteratively
    reweighted least squares) that the Marquardt loops, dense and structured, step with."""
    rho, drho = robust(loss, scale, r * r)
    w = jnp.sqrt(drho)
    return jnp.sum(rho), w * r, w[:, None] * J


def robust_change(loss: Loss | str, scale: float, r: Array, r_new: Array) -> Array:
    """Σ [ρ(r_new²) − ρ(r²)] computed term by term without cancellation.

    Taking the difference of the two sums loses every digit below eps·S, which stops the
    iteration long before x is as precise as float64 allows; (r_new − r)(r_new + r) does not.
    """
    ds = (r_new - r) * (r_new + r)  # s_new − s, accurate
    if loss == "huber":
        c2 = scale * scale
        s, s_new = r * r, r_new * r_new
        a, b = jnp.abs(r), jnp.abs(r_new)
        both_in = (s <= c2) & (s_new <= c2)
        both_out = (s > c2) & (s_new > c2)
        rho, _ = robust(loss, scale, s)
        rho_new, _ = robust(loss, scale, s_new)
        term = jnp.where(both_in, ds, jnp.where(both_out, 2.0 * scale * (b - a), rho_new - rho))
        return jnp.sum(term)
    if loss == "cauchy":
        c2 = scale * scale
        return jnp.sum(c2 * jnp.log1p(ds / (c2 + r * r)))
    return jnp.sum(ds)


@dataclass(frozen=True)
class LeastSquaresResult:
    """Every restart's outcome and the best one.

    Attributes
    ----------
    x : (R, n) float
        Final values of every restart.
    x0 : (R, n) float
        Their initial values.
    cost : (R,) float
        Final S (the robust cost Σρ(r²) when a robust loss is used); inf for failed restarts.
    status : (R,) int
        :class:`Status` codes.
    iterations : (R,) int
    best : int
        Index of the restart with the smallest finite cost (−1 when none is finite).
    active : (R, n) int or None
        With bounds: −1 where an unknown ends on its lower bound and the gradient pushes it
        further down (an *active* bound: the bound, not the data, decides its value), +1 on its
        upper bound pushed upwards, 0 elsewhere.  None when solved without bounds.
    """

    x: np.ndarray
    x0: np.ndarray
    cost: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    best: int
    config: SolverConfig = field(repr=False, default_factory=SolverConfig)
    active: np.ndarray | None = None

    @property
    def x_best(self) -> np.ndarray:
        if self.best < 0:
            return np.full(self.x.shape[1], np.nan)
        return self.x[self.best]

    @property
    def cost_best(self) -> float:
        return float(self.cost[self.best]) if self.best >= 0 else float("inf")

    @property
    def status_best(self) -> Status:
        return Status(int(self.status[self.best])) if self.best >= 0 else Status.NON_FINITE

    @property
    def converged(self) -> np.ndarray:
        return np.isin(self.status, [s.value for s in Status if s.converged])

    def statuses(self) -> list[Status]:
        return [Status(int(s)) for s in self.status]

    @property
    def active_best(self) -> np.ndarray:
        """(n,) the best restart's active bounds: −1 lower, +1 upper, 0 free (all 0 without bounds)."""
        if self.active is None or self.best < 0:
            return np.zeros(self.x.shape[1], dtype=np.int64)
        return np.asarray(self.active[self.best], dtype=np.int64)


class LocalParameterisation(Protocol):
    """Local coordinates for the solver's steps (a manifold step, as in Ceres and jaxlie).

    The solver linearises ``r(x ⊞ d)`` in d at d = 0 and moves to ``x ⊞ δ``.  The methods are
    traced with JAX; an object is compiled once per identity (keep the same object between
    calls).  :class:`mbcal.problem.Problem` provides one for roll-pitch-yaw orientations.

    Optional: ``represent_after(x, reference)``, :meth:`represent` on NumPy arrays of all restarts
    at once — x and reference (restarts, n), each restart's result and its start — returning the
    same shape.  When an object has it, the solver calls it once after the solve instead of
    tracing :meth:`represent` into its program (a shorter compile: issue 16).
    """

    def residual(self, x: Array, d: Array, *args: Array) -> Array:
        """The residual at x ⊞ d, differentiable in d at d = 0 (``args`` as for ``fun``).

        The solver evaluates it only at d = 0 (its value and its Jacobian in d there), so it may
        agree with ``r(plus(x, d))`` to first order only, where that is cheaper."""
        ...

    def plus(self, x: Array, d: Array) -> Array:
        """x ⊞ d: the point reached by the step d from x (x ⊞ 0 = x)."""
        ...

    def represent(self, x: Array, reference: Array) -> Array:
        """The coordinates of the same point nearest ``reference`` (where one point has several,
        as angles do); applied to each restart's result with its start as the reference."""
        ...


# Systems up to this size are solved by an unrolled Cholesky: under vmap it becomes a few fused
# vector operations across all restarts, where LAPACK would be called once per restart.
SMALL_SYSTEM = 16


def _solve_spd(M: Array, b: Array) -> Array:
    """Solve M x = b for a symmetric positive definite M (NaN when it is not).

    Used by :mod:`mbcal.structured` (issue 15): vmapped over thousands of small blocks (3 × 3,
    6 × 6) the unrolled factorisation is a few fused vector operations."""
    n = M.shape[0]
    if n > SMALL_SYSTEM:
        chol = jnp.linalg.cholesky(M)
        half = jax.scipy.linalg.solve_triangular(chol, b, lower=True)
        return jax.scipy.linalg.solve_triangular(chol.T, half, lower=False)
    # Scalar slots start as None placeholders; each is filled (with an Array) before it is read.
    L: list[list[Any]] = [[None] * n for _ in range(n)]
    for j in range(n):
        d = M[j, j] - sum((L[j][k] * L[j][k] for k in range(j)), start=0.0)
        L[j][j] = jnp.sqrt(d)  # NaN when M is not positive definite: the step is rejected
        for i in range(j + 1, n):
            L[i][j] = (M[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), start=0.0)) / L[j][j]
    y: list[Any] = [None] * n
    for i in range(n):
        y[i] = (b[i] - sum((L[i][k] * y[k] for k in range(i)), start=0.0)) / L[i][i]
    x: list[Any] = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), start=0.0)) / L[i][i]
    return jnp.stack(x)


# The normal equations of a batch of small systems (several restarts, m·n² up to this many
# products each) are summed elementwise: under vmap, XLA:CPU sent the matrix products of 64
# restarts of 96 × 6 or 168 × 7 to YNNPACK one small product at a time.  In-process A/B, 2 cores:
# the seed's warm solves 4.40 → 3.77 ms (room) and 21.5 → 19.4 ms (arm), compile unchanged
# (issue 16).  A single restart, or a larger system, keeps the matrix product: one restart of
# 144 × 18 ran 1.1–1.4× slower summed elementwise, one of 1,440 × 180 1.4–2.2× slower.
SMALL_NORMAL_EQUATIONS = 1 << 16


def normal_equations(J: Array, r: Array, elementwise: bool) -> tuple[Array, Array]:
    """JᵀJ and Jᵀr, by a sum of elementwise products (``elementwise``) or by matrix products."""
    if elementwise:
        return jnp.sum(J[:, :, None] * J[:, None, :], axis=0), jnp.sum(J * r[:, None], axis=0)
    return J.T @ J, J.T @ r


def _solve_step(M: Array, b: Array) -> Array:
    """Solve the damped normal equations M δ = b of the dense solver by LAPACK's Cholesky
    factorisation (NaN when M is not positive definite: the step is then rejected).

    Not :func:`_solve_spd`'s unrolled factorisation: vmapped over 64 restarts of 6–7 unknowns the
    two run equally fast, but the unrolled one doubled the XLA compile of the solver's own
    program (1.7 s → 0.9 s of CPU time; issue 16).  The structured solver solves its reduced
    system with it too.
    """
    chol = jnp.linalg.cholesky(M)
    half = jax.scipy.linalg.solve_triangular(chol, b, lower=True)
    return jax.scipy.linalg.solve_triangular(chol.T, half, lower=False)


# The resolution of a change of S = Σρ(r²) computed term by term (robust_change), relative to S:
# a few units of round-off per term, summed.
RESOLUTION = 16 * float(np.finfo(float).eps)


class Trial(NamedTuple):
    """One trial point of the Marquardt loop, judged: accepted or not, and the state it leaves."""

    first: Array
    ok: Array
    accept: Array
    actual: Array
    resolved: Array  # taken because S cannot resolve its change: converged to working precision
    x: Array
    r: Array
    rw: Array
    Jw: Array
    cost: Array
    lam: Array
    nu: Array


def marquardt_trial(evaluate: Callable, weighted: Callable, loss: Loss, scale: float, state: Any) -> Trial:
    """Evaluate the trial point ``state.x_try`` and apply Marquardt's rule (Nielsen's update of λ
    from the gain ratio ρ = actual / predicted decrease).  The one rule of the dense solver and of
    :mod:`mbcal.structured`: their iterates agree because this is shared, not copied.  ``state``
    has the fields x, r, rw, Jw, cost, x_try, predicted, lam, nu and it."""
    first = state.it == 0
    J_new, r_new = evaluate(state.x_try)
    cost_new, rw_new, Jw_new = weighted(r_new, J_new)
    ok = jnp.isfinite(cost_new) & jnp.all(jnp.isfinite(Jw_new))
    actual = jnp.where(first, jnp.inf, -robust_change(loss, scale, state.r, jnp.where(ok, r_new, state.r)))
    predicted = state.predicted
    # Near the minimum the decrease falls below what float64 resolves in S: the computed change is
    # rounding of either sign, and the rule "actual > 0" took or refused a sound Gauss–Newton step
    # by chance (a linear fit with tolerances of 1e-15 ended 1e-14 or 1e-10 from the solution
    # depending on how XLA ordered the sums).  A step whose predicted and computed changes are
    # both within that resolution is taken, and the loop reports S converged (working precision).
    resolution = RESOLUTION * (jnp.abs(state.cost) + jnp.abs(jnp.where(ok, cost_new, 0.0)))
    resolved = ok & ~first & (predicted > 0) & (predicted <= resolution) & (jnp.abs(actual) <= resolution)
    accept = ok & (first | (actual > 0) | resolved)
    rho = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0), -1.0)
    lam_acc = jnp.where(first | resolved, state.lam, state.lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3))
    return Trial(
        first=first,
        ok=ok,
        accept=accept,
        actual=actual,
        resolved=resolved,
        x=jnp.where(accept, state.x_try, state.x),
        r=jnp.where(accept, r_new, state.r),
        rw=jnp.where(accept, rw_new, state.rw),
        Jw=jnp.where(accept, Jw_new, state.Jw),
        cost=jnp.where(accept, jnp.where(first, cost_new, state.cost - actual), state.cost),
        lam=jnp.where(accept, lam_acc, state.lam * state.nu),
        nu=jnp.where(accept, 2.0, state.nu * 2.0),
    )


def step_status(config: SolverConfig, status: Array, finite_step: Array, delta: Array, x: Array, lam, it) -> Array:
    """The stopping tests after a step δ is computed (the first that holds wins): the step is tiny
    against ‖x‖, λ has grown past ``lambda_max``, or the iteration budget is spent.  Shared by the
    dense and the structured (:mod:`mbcal.structured`) loops."""
    step = jnp.sqrt(jnp.sum(delta * delta))
    xnorm = jnp.sqrt(jnp.sum(x * x))
    small = finite_step & (step <= config.xtol * (xnorm + config.xtol))
    status = jnp.where((status == 0) & small, Status.CONVERGED_STEP, status)
    status = jnp.where((status == 0) & (lam > config.lambda_max), Status.STALLED, status)
    return jnp.where((status == 0) & (it >= config.max_iterations), Status.MAX_ITERATIONS, status)


def active_set(x: Array, g: Array, lower: Array, upper: Array) -> Array:
    """The unknowns a projected step holds: on a bound, with the gradient g of S pushing them
    outwards (S decreases along −g).  The one rule of the dense and the structured
    (:mod:`mbcal.structured`) loops with hard bounds."""
    return ((x <= lower) & (g > 0)) | ((x >= upper) & (g < 0))


def projected(x: Array, delta: Array, lower: Array, upper: Array) -> Array:
    """The step actually taken after the projection onto the bounds: clip(x + δ) − x, written as
    δ + (clip(x + δ) − (x + δ)) (local coordinates are never bounded)."""
    moved = x + delta
    return delta + (jnp.clip(moved, lower, upper) - moved)


def active_at_end(x: Array, g: Array, column_norm: Array, residual_norm: Array, lower, upper, gtol) -> Array:
    """−1 / +1 / 0 per unknown: on its lower / upper bound with a gradient that pushes it outwards
    by more than ``gtol`` (scale-free, as the gradient test: an unknown no measurement sees stays
    free, σ = ∞), else 0.  ``column_norm``: ‖J_j‖; ``residual_norm``: ‖r‖ (weighted)."""
    pushed = jnp.abs(g) > gtol * (column_norm * residual_norm)
    lower_active = (x <= lower) & (g > 0) & pushed
    upper_active = (x >= upper) & (g < 0) & pushed
    return jnp.where(lower_active, -1, jnp.where(upper_active, 1, 0)).astype(jnp.int32)


def hard_limits(
    bounds: tuple[Array, Array] | None, x0: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray] | None, np.ndarray]:
    """Checked hard bounds for starts ``x0`` (R, n) and the starts moved inside them: (None, x0)
    when there are none or every side is infinite (then the unbounded program runs)."""
    if bounds is None:
        return None, x0
    if len(bounds) != 2:
        raise SolverError(f"bounds must be (lower, upper), got {len(bounds)} item(s)")
    for side, name in zip(bounds, ("lower", "upper")):
        given = np.shape(side)
        if given not in ((), x0.shape[1:]):  # one number for all, or one per unknown: never spread
            raise SolverError(
                f"bounds: the {name} bounds have shape {given}; give one number or one per unknown {x0.shape[1:]}"
            )
    lower = np.broadcast_to(np.asarray(bounds[0], dtype=float), x0.shape[1:]).copy()
    upper = np.broadcast_to(np.asarray(bounds[1], dtype=float), x0.shape[1:]).copy()
    if np.any(np.isnan(lower)) or np.any(np.isnan(upper)) or np.any(lower > upper):
        raise SolverError("bounds must be numbers (±inf for none) with lower ≤ upper")
    if not (np.any(np.isfinite(lower)) or np.any(np.isfinite(upper))):
        return None, x0
    return (lower, upper), np.clip(x0, lower, upper)


class _LMState(NamedTuple):
    """The Marquardt loop's carry (a pytree: JAX traces its fields)."""

    x: Array  # (n,) the accepted point
    r: Array  # (m,) its residual
    rw: Array  # (m,) the residual weighted by the robust loss
    Jw: Array  # (n² + n,) the normal equations JwᵀJw and Jwᵀrw at x, packed: not the (m, n) Jacobian
    cost: Array  # Σρ(r²) at x
    x_try: Array  # (n,) the trial point the next iteration evaluates
    predicted: Array  # the decrease of S the linear model predicts for the trial step
    lam: Array  # λ
    nu: Array  # λ's growth factor after a rejected step (Nielsen)
    D: Array  # (n,) running maximum of diag(JᵀJ): Marquardt's scaling
    it: Array  # iterations done
    status: Array  # 0 while running, else a Status code


def restart_loop(cond: Callable, body: Callable, state0: Any) -> Any:
    """``vmap(lambda s: lax.while_loop(cond, body, s))(state0)``: one restart per entry of the
    leading axis of every field of ``state0``, ``cond`` and ``body`` written for one restart.

    It computes what JAX's batching rule for a while loop computes — the loop runs while any
    restart's ``cond`` holds; each iteration evaluates ``body`` for every restart and keeps the new
    state only where ``cond`` held, so a finished restart is frozen (bit for bit the same results)
    — with every field batched from the start.  vmap of a loop whose state began unbatched (λ,
    the counters, the zero residual) re-batched the whole traced body until the batched fields
    reached a fixed point (4–5 passes): the room's trace + lower 0.43 → 0.32 s (issue 16).  Shared
    by the dense and the structured (:mod:`mbcal.structured`) solvers."""
    vcond, vbody = jax.vmap(cond), jax.vmap(body)

    def step(state):
        running = vcond(state)
        new = vbody(state)

        def keep(a, b):
            # lax.select, not jnp.where: the same selection without a nested jit per field.
            return jax.lax.select(jax.lax.broadcast_in_dim(running, a.shape, (0,)), a, b)

        return jax.tree.map(keep, new, state)

    return jax.lax.while_loop(lambda state: jnp.any(vcond(state)), step, state0)


def _lm_batch(
    fun: Callable,
    config: SolverConfig,
    x0s: Array,
    args: tuple,
    m: int,
    bounds: tuple[Array, Array] | None = None,
    local: LocalParameterisation | None = None,
    represent: bool = True,
) -> tuple:
    """Marquardt iterations from each start (rows of ``x0s``); returns (x, cost, status,
    iterations) per start, and with ``bounds`` also the active bounds at the end (−1, 0, +1 per
    unknown).

    The loop body evaluates the residual and Jacobian once, at the trial point the previous
    iteration proposed (the first iteration evaluates x0), so the model is traced only once.
    Without ``bounds`` and ``local`` the traced program is exactly the plain Marquardt loop.
    """
    loss, scale = config.loss, config.loss_scale
    assert scale is not None  # SolverConfig.__post_init__ replaces None with the loss's default
    n = x0s.shape[1]
    elementwise = x0s.shape[0] > 1 and m * n * n <= SMALL_NORMAL_EQUATIONS

    if local is None:

        def evaluate(x):
            # One forward-mode pass gives the Jacobian and, as auxiliary output, the residual itself.
            return jax.jacfwd(lambda z: (lambda r: (r, r))(fun(z, *args)), has_aux=True)(x)

    else:
        zero_step = jnp.zeros(n)

        def evaluate(x):
            # The Jacobian in the local coordinates about x: ∂r(x ⊞ d)/∂d at d = 0.
            return jax.jacfwd(lambda d: (lambda r: (r, r))(local.residual(x, d, *args)), has_aux=True)(zero_step)

    def weighted(r, J):
        # The loop keeps the normal equations, not the weighted Jacobian: the Marquardt step, the
        # gradient test and the active bounds need only JᵀJ and Jᵀr, and carrying (and selecting)
        # the m × n Jacobian every iteration was a third of the room's loop (issue 16).
        cost, rw, Jw = robust_system(loss, scale, r, J)
        A, g = normal_equations(Jw, rw, elementwise)
        return cost, rw, jnp.concatenate([jnp.ravel(A), g])

    def unpack(N):
        return N[: n * n].reshape(n, n), N[n * n :]

    def held(x, g):
        assert bounds is not None
        return active_set(x, g, bounds[0], bounds[1])

    def gradient_small(rw, A, g, x):
        if bounds is not None:
            g = jnp.where(held(x, g), 0.0, g)  # the projected gradient
        col = jnp.sqrt(jnp.diag(A))
        rn = jnp.sqrt(jnp.sum(rw * rw))
        denom = col * rn
        cosine = jnp.where(denom > 0, jnp.abs(g) / jnp.where(denom > 0, denom, 1.0), 0.0)
        return jnp.max(cosine, initial=0.0) <= config.gtol

    def start(x0):
        return _LMState(
            x=x0,
            r=jnp.zeros(m),
            rw=jnp.zeros(m),
            Jw=jnp.zeros(n * n + n),
            cost=jnp.asarray(jnp.inf),
            x_try=x0,
            predicted=jnp.asarray(0.0),
            lam=jnp.asarray(config.lambda_init),
            nu=jnp.asarray(2.0),
            D=jnp.zeros(n),
            it=jnp.int32(0),
            status=jnp.int32(0),
        )

    def cond(state: _LMState):
        return state.status == 0

    def body(state: _LMState) -> _LMState:
        x, r, rw, Jw, cost, x_try, predicted, lam, nu, D, it, status = state
        trial = marquardt_trial(evaluate, weighted, loss, scale, state)
        first, ok, accept, actual = trial.first, trial.ok, trial.accept, trial.actual
        x, r, rw, Jw, cost, lam, nu = trial.x, trial.r, trial.rw, trial.Jw, trial.cost, trial.lam, trial.nu
        it = it + 1
        # Convergence of the step just taken.
        status = jnp.where(first & ~ok, Status.NON_FINITE, 0)
        tiny = trial.resolved | ((actual <= config.ftol * cost) & (predicted <= config.ftol * cost))
        status = jnp.where((status == 0) & accept & ~first & tiny, Status.CONVERGED_COST, status)
        status = jnp.where((status == 0) & accept & (cost == 0), Status.CONVERGED_COST, status)
        A, g = unpack(Jw)
        status = jnp.where((status == 0) & accept & gradient_small(rw, A, g, x), Status.CONVERGED_GRADIENT, status)
        # The next trial point.
        D = jnp.maximum(D, jnp.diag(A))
        Dc = jnp.maximum(D, 1e-12 * jnp.maximum(jnp.max(D), 1e-300))
        if bounds is None:
            delta = _solve_step(A + lam * jnp.diag(Dc), -g)
        else:
            # Active unknowns are held: their rows and columns of the damped system become the identity.
            free = ~held(x, g)
            both = free[:, None] & free[None, :]
            M = jnp.where(both, A + lam * jnp.diag(Dc), 0.0) + jnp.diag(jnp.where(free, 0.0, 1.0))
            delta = _solve_step(M, jnp.where(free, -g, 0.0))
        finite_step = jnp.all(jnp.isfinite(delta))
        delta = jnp.where(finite_step, delta, 0.0)
        if bounds is None:
            taken = delta
        else:
            taken = projected(x, delta, bounds[0], bounds[1])  # the step actually taken
        predicted = jnp.where(finite_step, -(2.0 * g @ taken + taken @ (A @ taken)), -1.0)
        status = step_status(config, status, finite_step, delta, x, lam, it)
        # A step that cannot be computed is a rejection: try again with a larger λ.
        x_next = x + delta if local is None else local.plus(x, delta)
        if bounds is not None:
            x_next = jnp.clip(x_next, bounds[0], bounds[1])
        x_try = jnp.where(finite_step, x_next, x)
        return _LMState(x, r, rw, Jw, cost, x_try, predicted, lam, nu, D, it, status.astype(jnp.int32))

    def final_active(final: _LMState) -> Array:
        assert bounds is not None
        A, g = unpack(final.Jw)
        rn = jnp.sqrt(jnp.sum(final.rw * final.rw))
        return active_at_end(final.x, g, jnp.sqrt(jnp.diag(A)), rn, bounds[0], bounds[1], config.gtol)

    def finish(final: _LMState, x0: Array) -> tuple:
        # The running cost accumulates exact changes; report the cost of the final residual itself.
        cost = jnp.where(
            final.status == Status.NON_FINITE, jnp.inf, robust_system(loss, scale, final.r, jnp.zeros((m, 1)))[0]
        )
        # ``represent``: local.represent in the program (else represent_after runs after it); the
        # active bounds are those of the solver's own x, as by blocks (mbcal.structured)
        x = local.represent(final.x, x0) if local is not None and represent else final.x
        if bounds is None:
            return x, cost, final.status, final.it
        return x, cost, final.status, final.it, final_active(final)

    final = restart_loop(cond, body, jax.vmap(start)(x0s))
    return jax.vmap(finish)(final, x0s)


class _Identity:
    """Wraps an object so that the compiled-code cache keys on its identity."""

    __slots__ = ("obj",)

    def __init__(self, obj: Any):
        self.obj = obj

    def __hash__(self) -> int:
        return id(self.obj)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Identity) and other.obj is self.obj


def represented_in_program(local: LocalParameterisation | None) -> bool:
    """Whether ``local.represent`` is traced into the solver's program (it has no ``represent_after``)."""
    return local is not None and not hasattr(local, "represent_after")


def represented_after(local: LocalParameterisation, x: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """The results ``x`` (restarts, n) through ``local.represent_after`` (the caller's object: a
    wrong shape is said in its name)."""
    after: Callable[[np.ndarray, np.ndarray], Any] = local.represent_after  # type: ignore[attr-defined]
    out = np.asarray(after(x, x0), dtype=np.float64)
    if out.shape != x.shape:
        raise SolverError(
            f"{type(local).__name__}.represent_after returned shape {out.shape} for results of shape {x.shape}",
            hint="it takes and returns every restart's result at once, one row each",
        )
    return out


class _StagedLocal:
    """A local parameterisation whose residual is a staged program (:mod:`mbcal.staging`): it takes
    the recipe's inputs in place of the residual's arguments."""

    def __init__(self, local: LocalParameterisation, program: Callable):
        self._local, self._program = local, program

    def residual(self, x: Array, d: Array, *inputs: Array) -> Array:
        return self._program(x, d, *inputs)

    def plus(self, x: Array, d: Array) -> Array:
        return self._local.plus(x, d)

    def represent(self, x: Array, reference: Array) -> Array:
        return self._local.represent(x, reference)


@functools.lru_cache(maxsize=8)
def _staged_local(local: _Identity, program: Callable) -> _StagedLocal:
    """One object per parameterisation and program: the solver's programs compiled for it are found
    again (they are cached per identity)."""
    return _StagedLocal(local.obj, program)


# A few programs only: each compiled solver holds a few hundred memory maps of XLA's code (338 for
# the room's), and a long process (the test suite) that kept 64 alive came near the kernel's limit
# of 65,530 maps, where XLA:CPU crashes (issue 16).  Problems of one structure share one entry.
@functools.lru_cache(maxsize=8)
def _compiled(
    fun: Callable,
    config: SolverConfig,
    size: int | None = None,
    bounded: bool = False,
    wrapped: _Identity | None = None,
    represent: bool = True,
) -> Callable:
    local: LocalParameterisation | None = None if wrapped is None else wrapped.obj

    def residuals(x0s, args):
        # The number of residuals: given, or from a cheap abstract trace (a caller's own function:
        # what it returns is checked, not left to fail inside the program with JAX's words)
        if size is not None:
            return size
        out = jax.eval_shape(fun, x0s[0], *args)
        shape, dtype = getattr(out, "shape", None), getattr(out, "dtype", None)
        if shape is None or len(shape) != 1 or not jnp.issubdtype(dtype, jnp.floating):
            raise SolverError(
                "the residual function must return a 1-D array of real numbers (m,), got "
                + (f"shape {tuple(shape)} of {dtype}" if shape is not None else type(out).__name__),
                hint="return jnp.ravel(r) for an array of residuals; split a complex one into real and imaginary parts",
            )
        return shape[0]

    if not bounded:

        def batch(x0s, args):
            m = residuals(x0s, args)
            return _lm_batch(fun, config, x0s, args, m, None, local, represent)

        return jit(batch)

    def batch_bounded(x0s, args, lower, upper):
        m = residuals(x0s, args)
        return _lm_batch(fun, config, x0s, args, m, (lower, upper), local, represent)

    return jit(batch_bounded)


@in_float64
def least_squares(
    fun: Callable[..., Array],
    x0: Array,
    *,
    args: tuple = (),
    config: SolverConfig | None = None,
    size: int | None = None,
    cache_key: str | None = None,
    bounds: tuple[Array, Array] | None = None,
    local: LocalParameterisation | None = None,
) -> LeastSquaresResult:
    """Minimise ``Σ ρ(r_i²)`` for ``r = fun(x, *args)`` from one or many starting points.

    Parameters
    ----------
    fun : callable
        ``fun(x, *args) -> r``: the whitened residual vector (m,) for parameters x (n,), written
        with ``jax.numpy`` so that it can be traced and differentiated.  Keep the same function
        object between calls: compiled code is cached per function and config.
    x0 : (n,) or (R, n) array
        Starting point(s); each row is one restart, all run in one vmapped, compiled call.
    args : tuple of arrays
        Extra inputs of ``fun`` (measurements, known values) — changing them does not recompile.
        What ``fun`` computes from them alone is computed in NumPy before the compiled program
        runs (:mod:`mbcal.staging`; the same residual to rounding).
    config : SolverConfig, optional
    size : int, optional
        The number of residuals, when known (saves one trace of ``fun``).
    cache_key : str, optional
        A fingerprint of everything ``fun`` depends on besides ``args`` (see :mod:`mbcal.cache`):
        the traced program is then saved and a later process reuses it without tracing.  With
        ``local`` it must cover what ``local`` depends on as well.
    bounds : (lower, upper) of (n,) arrays, optional
        Hard bounds (±inf: none on that side).  Every iterate stays inside (projected steps:
        see the module's documentation); starting points outside are moved onto the nearest
        bound.  None (or all infinite): no bounds, and the very program that runs without them.
    local : LocalParameterisation, optional
        Local coordinates to step in (used when ``config.manifold`` is true; see
        :class:`LocalParameterisation`).  Bounded unknowns must be stepped additively by it.

    Returns
    -------
    LeastSquaresResult
        Every restart's x, cost, status and iteration count, the index of the best, and with
        bounds the active bounds of every restart.
    """
    config = config or SolverConfig()
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    if x0.ndim != 2 or 0 in x0.shape:
        raise SolverError(f"x0 must be (n,) or (restarts, n) with n ≥ 1, got shape {x0.shape}")
    args = tuple(as_argument(a) for a in args)  # not jnp.asarray: it compiles a program per shape
    local = local if config.manifold else None
    in_program = represented_in_program(local)  # decided once: the program and what follows it agree
    limits, x0 = hard_limits(bounds, x0)
    key = recipe_key = None
    given = (fun, args, local)
    if cache_key is not None:
        # weak types too: they change how a traced program promotes types
        signature = [(a.shape, str(a.dtype), bool(getattr(a, "weak_type", False))) for a in args]
        key = Hasher().add(cache_key, repr(config), size, x0.shape, signature)
        if limits is not None:
            key.add("bounded")
        if local is not None:
            key.add("local", type(local).__module__, type(local).__qualname__, in_program)
    if args and (local is None or size is not None):
        # What depends on the known arguments only is computed before the program (mbcal.staging).
        # (With local coordinates the solver traces local.residual, and fun only for the size.)
        unknowns = (x0[0],) if local is None else (x0[0], np.zeros(x0.shape[1]))
        recipe_key = None if key is None else key.copy().add("staged").hexdigest()
        staged = prepare(fun if local is None else local.residual, unknowns, args, recipe_key)
        if staged is not None:
            program_fun, args, digest = staged
            if local is None:
                fun = program_fun
            else:
                local = _staged_local(_Identity(local), program_fun)
            if key is not None:
                key.add("staged", digest)  # the exported program is the one made for this recipe
    program = _compiled(fun, config, size, limits is not None, local if local is None else _Identity(local), in_program)
    example: tuple[Any, ...] = (x0, args)
    if limits is not None:
        example += limits
    try:
        if key is not None:
            program = exported(key.hexdigest(), program, *example)
        out = program(*example)
    except StaleRecipeError:
        # the cached recipe is not this process's split of fun (another JAX): solve without it
        if recipe_key is not None:
            forget(recipe_key)
        fun, args, local = given
        return least_squares(fun, x0, args=args, config=config, size=size, bounds=bounds, local=local)
    except _RUNTIME_ERROR as err:
        raise _out_of_memory(err, x0, size) from None
    try:
        x, cost, status, it = (np.asarray(v) for v in out[:4])  # where XLA's run ends (dispatch is asynchronous)
        active = np.asarray(out[4]) if limits is not None else None
    except _RUNTIME_ERROR as err:
        raise _out_of_memory(err, x0, size) from None
    if given[2] is not None and not in_program:  # each result in the coordinates nearest its start
        x = represented_after(given[2], x, x0)
    finite = np.isfinite(cost)
    best = int(np.argmin(np.where(finite, cost, np.inf))) if finite.any() else -1
    return LeastSquaresResult(
        x=x, x0=x0, cost=cost, status=status, iterations=it, best=best, config=config, active=active
    )


# XLA's failures at run time (JaxRuntimeError from JAX 0.4.34; before it, jaxlib's XlaRuntimeError, a
# RuntimeError): looked up so that an older JAX, which pyproject.toml allows, does not fail on the name.
_RUNTIME_ERROR: type[Exception] = getattr(jax.errors, "JaxRuntimeError", RuntimeError)


def _out_of_memory(err: Exception, x0: np.ndarray, size: int | None) -> Exception:
    """A batch that did not fit in memory as an error of the input (not a traceback); any other
    runtime error as it was."""
    if "RESOURCE_EXHAUSTED" not in str(err):
        return err
    rows = "" if size is None else f" over {size} residual rows"
    return SolverError(
        f"{x0.shape[0]} restarts of {x0.shape[1]} unknowns{rows} did not fit in memory ({str(err).splitlines()[0]})",
        hint="use fewer restarts (--restarts), fewer measurements, or a coarser scan (--voxel)",
    )


def random_starts(
    x_init: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    restarts: int,
    seed: int | None,
    limits: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """(restarts, n) starting points: the first is ``x_init``; the others are drawn uniformly in
    [lower, upper] where both are finite, and equal ``x_init`` elsewhere.  With ``limits``
    (hard bounds) every start is then moved inside them (the draws themselves are unchanged)."""
    n = len(x_init)
    out = np.tile(np.asarray(x_init, dtype=float), (max(1, restarts), 1))
    ranged = np.isfinite(lower) & np.isfinite(upper)
    if restarts > 1 and ranged.any():
        draws = np.random.default_rng(seed).uniform(size=(restarts - 1, n))
        span = np.where(ranged, upper - lower, 0.0)
        base = np.where(ranged, lower, 0.0)
        out[1:] = np.where(ranged, base + draws * span, out[1:])
    if limits is not None:
        out = np.clip(out, limits[0], limits[1])
    return out


# ---- sizes refused before anything is allocated (every command and API that solves) ----------------

MAX_RESTARTS = 10_000
"""The most starting points one calibration runs: they run as one vmapped batch, and a few dozen
are plenty (docs/reliability.md)."""

MAX_DENSE_UNKNOWNS = 10_000
"""The most unknowns of the dense solver and analysis: each restart holds an n × n normal matrix
(10 000² × 8 bytes = 800 MB) and the analysis an SVD of the m × n Jacobian."""

MAX_SOLVER_BYTES = 32 * 2**30
"""The most memory (32 GiB) the batch's dense Jacobians and normal matrices may need, estimated as
8 bytes × restarts × (rows × unknowns + 2 × unknowns²); less on a machine with less than twice
that memory (:func:`solver_byte_limit`)."""


def solver_byte_limit() -> int:
    """:data:`MAX_SOLVER_BYTES`, or half the machine's physical memory where that is less: a batch
    the machine cannot hold was a JAX out-of-memory traceback (10 000 restarts of a scan fit on
    24 GiB), not an error before the work."""
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):  # not on this platform: the fixed limit
        return MAX_SOLVER_BYTES
    return min(MAX_SOLVER_BYTES, physical // 2) if physical > 0 else MAX_SOLVER_BYTES


def check_size(restarts: int, unknowns: int = 0, rows: int = 0) -> None:
    """Refuse absurd problem sizes before anything is allocated (a :class:`SolverError` with a hint)."""
    if restarts < 1:
        raise SolverError(f"restarts must be at least 1, got {restarts}", hint="--restarts N with N ≥ 1")
    if restarts > MAX_RESTARTS:
        raise SolverError(
            f"{restarts} restarts is more than mbcal runs ({MAX_RESTARTS}): they run as one batch in memory",
            hint="a few dozen restarts are plenty (the default is 16; the CLI's 32)",
        )
    if unknowns > MAX_DENSE_UNKNOWNS:
        raise SolverError(
            f"{unknowns} unknowns is more than the dense solver handles ({MAX_DENSE_UNKNOWNS}): "
            f"each restart would hold a {unknowns} × {unknowns} matrix ({8 * unknowns**2 / 2**30:.3g} GiB)",
            hint="estimate fewer unknowns at once (--estimate), or fix per-configuration parameters that are known",
        )
    need = 8.0 * restarts * (float(rows) * unknowns + 2.0 * float(unknowns) ** 2)
    limit = solver_byte_limit()
    if need > limit:
        raise SolverError(
            f"{restarts} restarts of {unknowns} unknowns over {rows} residual rows would need about "
            f"{need / 2**30:.3g} GiB of dense Jacobians (the limit is {limit / 2**30:.3g} GiB: "
            "32 GiB, or half the machine's memory where that is less)",
            hint="use fewer restarts (--restarts), fewer unknowns, or fewer measurements",
        )
