"""Marquardt's method with random restarts, compiled with JAX (seed, section 3.4, eqs. 15–18).

Each iteration solves ``(JᵀJ + λ·D) δ = −Jᵀr`` for the whitened residual r = W^½ (h(x) − y) and
its Jacobian J = W^½ ∂h/∂x, where D is the diagonal of JᵀJ as Marquardt proposed (kept as a
running maximum, as MINPACK does, so a column that vanishes does not make the system singular).
λ adapts to the nonlinearity by the gain ratio (Nielsen's rule). J comes from ``jax.jacfwd``
together with r in one pass. The whole iteration loop is one ``lax.while_loop``; all restarts run
vmapped in one compiled call, a restart that finishes is frozen while the others go on, and a
restart that fails (non-finite residuals) gets its status without stopping the batch.

The low-level entry point :func:`least_squares` solves any residual function, so the solver
serves beyond .mdl models (the NIST StRD tests use it directly).
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp

Array = Any

__all__ = ["Status", "SolverConfig", "Loss", "LeastSquaresResult", "least_squares", "random_starts"]


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
    Status.CONVERGED_COST: "converged: S changed by less than ftol (relative)",
    Status.CONVERGED_STEP: "converged: the step is smaller than xtol (relative)",
    Status.CONVERGED_GRADIENT: "converged: the gradient is orthogonal to the residuals within gtol",
    Status.MAX_ITERATIONS: "stopped: the iteration limit was reached before convergence",
    Status.NON_FINITE: "failed: the residuals are not finite at the initial values",
    Status.STALLED: "stopped: λ grew past its limit without reducing S (a saddle, a bound of the model, or "
    "numerical noise)",
}


class Loss(enum.Enum):
    """Robust loss ρ(s) applied to each squared whitened residual s = r²."""

    LINEAR = "linear"
    HUBER = "huber"
    CAUCHY = "cauchy"


@dataclass(frozen=True)
class SolverConfig:
    """Settings of the Marquardt solver.

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
    loss : str
        ``linear`` (least squares), ``huber`` or ``cauchy``.
    loss_scale : float
        Scale c of the robust loss, in units of the whitened residual (σ): residuals below c
        count quadratically.
    """

    max_iterations: int = 100
    ftol: float = 1e-15
    xtol: float = 1e-15
    gtol: float = 1e-15
    lambda_init: float = 1e-3
    lambda_max: float = 1e16
    loss: str = "linear"
    loss_scale: float = 1.0

    def __post_init__(self) -> None:
        from mbcal.errors import SolverError

        try:
            Loss(self.loss)
        except ValueError:
            raise SolverError(f"unknown loss '{self.loss}' (linear, huber or cauchy)") from None
        if not self.loss_scale > 0:
            raise SolverError(f"loss_scale must be positive, got {self.loss_scale}")
        if self.max_iterations < 1:
            raise SolverError("max_iterations must be at least 1")


def robust(loss: str, scale: float, s: Array) -> tuple[Array, Array]:
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


def robust_change(loss: str, scale: float, r: Array, r_new: Array) -> Array:
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
    """

    x: np.ndarray
    x0: np.ndarray
    cost: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    best: int
    config: SolverConfig = field(repr=False, default_factory=SolverConfig)

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


def _lm_single(fun: Callable, config: SolverConfig, x0: Array, args: tuple) -> tuple:
    """Marquardt iterations from one start; returns (x, cost, status, iterations)."""
    loss, scale = config.loss, config.loss_scale

    def evaluate(x):
        # One forward-mode pass gives the Jacobian and, as auxiliary output, the residual itself.
        return jax.jacfwd(lambda z: (lambda r: (r, r))(fun(z, *args)), has_aux=True)(x)

    def weighted(r, J):
        s = r * r
        rho, drho = robust(loss, scale, s)
        w = jnp.sqrt(drho)
        return jnp.sum(rho), w * r, w[:, None] * J

    J0, r0 = evaluate(x0)
    cost0, rw0, Jw0 = weighted(r0, J0)
    finite0 = jnp.isfinite(cost0) & jnp.all(jnp.isfinite(Jw0))
    A0 = Jw0.T @ Jw0
    D0 = jnp.diag(A0)
    n = x0.shape[0]

    def gradient_test(rw, Jw):
        g = Jw.T @ rw
        col = jnp.sqrt(jnp.sum(Jw * Jw, axis=0))
        rn = jnp.sqrt(jnp.sum(rw * rw))
        denom = col * rn
        cosine = jnp.where(denom > 0, jnp.abs(g) / jnp.where(denom > 0, denom, 1.0), 0.0)
        return jnp.max(cosine, initial=0.0) <= config.gtol

    status0 = jnp.where(
        finite0,
        jnp.where((cost0 == 0) | gradient_test(rw0, Jw0), Status.CONVERGED_GRADIENT, 0),
        Status.NON_FINITE,
    ).astype(jnp.int32)
    state0 = (x0, r0, rw0, Jw0, cost0, jnp.asarray(config.lambda_init), jnp.asarray(2.0), D0, jnp.int32(0), status0)

    def cond(state):
        return state[-1] == 0

    def body(state):
        x, r, rw, Jw, cost, lam, nu, D, it, status = state
        A = Jw.T @ Jw
        g = Jw.T @ rw
        D = jnp.maximum(D, jnp.diag(A))
        Dc = jnp.maximum(D, 1e-12 * jnp.maximum(jnp.max(D), 1e-300))
        M = A + lam * jnp.diag(Dc)
        L = jnp.linalg.cholesky(M)
        y = jax.scipy.linalg.solve_triangular(L, -g, lower=True)
        delta = jax.scipy.linalg.solve_triangular(L.T, y, lower=False)
        x_new = x + delta
        J_new, r_new = evaluate(x_new)
        cost_new, rw_new, Jw_new = weighted(r_new, J_new)
        ok = jnp.isfinite(cost_new) & jnp.all(jnp.isfinite(Jw_new)) & jnp.all(jnp.isfinite(delta))
        predicted = -(2.0 * g @ delta + delta @ (A @ delta))
        actual = -robust_change(loss, scale, r, jnp.where(ok, r_new, r))
        rho = jnp.where(predicted > 0, actual / jnp.where(predicted > 0, predicted, 1.0), -1.0)
        accept = ok & (actual > 0)
        # Nielsen's update of λ.
        lam_acc = lam * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        lam_new = jnp.where(accept, lam_acc, lam * nu)
        nu_new = jnp.where(accept, 2.0, nu * 2.0)
        step = jnp.sqrt(jnp.sum(jnp.where(jnp.isfinite(delta), delta, 0.0) ** 2))
        xnorm = jnp.sqrt(jnp.sum(x * x))
        small_step = step <= config.xtol * (xnorm + config.xtol)
        x2 = jnp.where(accept, x_new, x)
        r2 = jnp.where(accept, r_new, r)
        rw2 = jnp.where(accept, rw_new, rw)
        Jw2 = jnp.where(accept, Jw_new, Jw)
        cost2 = jnp.where(accept, cost - actual, cost)
        it2 = it + 1
        new_status = jnp.int32(0)
        # MINPACK's test: both the actual and the predicted reduction are below ftol (relative).
        tiny_change = (actual <= config.ftol * cost) & (predicted <= config.ftol * cost)
        new_status = jnp.where(accept & tiny_change, Status.CONVERGED_COST, new_status)
        new_status = jnp.where(accept & (cost2 == 0), Status.CONVERGED_COST, new_status)
        new_status = jnp.where(
            (new_status == 0) & accept & gradient_test(rw2, Jw2), Status.CONVERGED_GRADIENT, new_status
        )
        new_status = jnp.where((new_status == 0) & small_step & ok, Status.CONVERGED_STEP, new_status)
        new_status = jnp.where((new_status == 0) & (lam_new > config.lambda_max), Status.STALLED, new_status)
        new_status = jnp.where((new_status == 0) & (it2 >= config.max_iterations), Status.MAX_ITERATIONS, new_status)
        return (x2, r2, rw2, Jw2, cost2, lam_new, nu_new, D, it2, new_status.astype(jnp.int32))

    x, r, rw, Jw, cost, lam, nu, D, it, status = jax.lax.while_loop(cond, body, state0)
    # The running cost accumulates exact changes; report the cost of the final residual itself.
    cost = jnp.where(status == Status.NON_FINITE, jnp.inf, weighted(r, jnp.zeros((r.shape[0], 1)))[0])
    del n, rw, Jw, lam, nu, D
    return x, cost, status, it


@functools.lru_cache(maxsize=64)
def _compiled(fun: Callable, config: SolverConfig) -> Callable:
    def batch(x0s, args):
        return jax.vmap(lambda x0: _lm_single(fun, config, x0, args))(x0s)

    return jax.jit(batch)


def least_squares(
    fun: Callable[..., Array],
    x0: Array,
    *,
    args: tuple = (),
    config: SolverConfig | None = None,
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
    config : SolverConfig, optional

    Returns
    -------
    LeastSquaresResult
        Every restart's x, cost, status and iteration count, and the index of the best.
    """
    config = config or SolverConfig()
    x0 = np.atleast_2d(np.asarray(x0, dtype=float))
    args = tuple(jnp.asarray(a) for a in args)
    x, cost, status, it = _compiled(fun, config)(jnp.asarray(x0), args)
    x, cost, status, it = (np.asarray(v) for v in (x, cost, status, it))
    finite = np.isfinite(cost)
    best = int(np.argmin(np.where(finite, cost, np.inf))) if finite.any() else -1
    return LeastSquaresResult(x=x, x0=x0, cost=cost, status=status, iterations=it, best=best, config=config)


def random_starts(
    x_init: np.ndarray, lower: np.ndarray, upper: np.ndarray, restarts: int, seed: int | None
) -> np.ndarray:
    """(restarts, n) starting points: the first is ``x_init``; the others are drawn uniformly in
    [lower, upper] where both are finite, and equal ``x_init`` elsewhere."""
    rng = np.random.default_rng(seed)
    n = len(x_init)
    out = np.tile(np.asarray(x_init, dtype=float), (max(1, restarts), 1))
    ranged = np.isfinite(lower) & np.isfinite(upper)
    if restarts > 1 and ranged.any():
        draws = rng.uniform(size=(restarts - 1, n))
        span = np.where(ranged, upper - lower, 0.0)
        base = np.where(ranged, lower, 0.0)
        out[1:] = np.where(ranged, base + draws * span, out[1:])
    return out
