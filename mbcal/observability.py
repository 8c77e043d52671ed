"""Observability and uncertainty at a solution (seed 3.4, and beyond it).

At x the whitened Jacobian J = W^½ ∂h/∂x says everything: its singular values give the rank and
the condition number; the right singular vectors of the (numerically) zero singular values are
the directions in parameter space that no measurement sees — named here in the user's
parameter names; (JᵀJ)⁻¹ on the observable subspace is the covariance of the estimate.  Rank
decisions are made on J with its columns scaled by each unknown's natural scale (half its
search range, else its prior σ, else one SI unit or its nominal magnitude), so metres and
radians, pixels and focal lengths are compared fairly.

An unknown held at an *active* hard bound (the solver's ``active``: on a limit, with the data
pushing it further out) is determined by the bound, not by the measurements: the analysis treats
it as fixed — rank, condition, the named combinations and the covariance are those of the other
unknowns with it held, its σ is 0 and its rows and columns of the covariance are 0 (NaN
correlations) — and :attr:`Observability.active_bounds` names it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar, overload

import numpy as np

from mbcal.units import to_display

__all__ = [
    "Combination",
    "Observability",
    "ObservabilityConfig",
    "analyze",
    "unknown_scales",
    "scale_sources",
    "scale_stand_ins",
    "weak_scale_text",
    "yardstick_text",
    "PointUncertainty",
    "PointUncertainties",
    "PointLabels",
    "MadeWhenRead",
    "point_uncertainty",
    "point_uncertainties",
]


@dataclass(frozen=True)
class ObservabilityConfig:
    """Tolerances of the observability analysis.

    Attributes
    ----------
    rtol : float
        A scaled singular value below ``rtol · σ_max`` counts as zero (an unobservable direction).
    weak : float
        A direction is *weakly* observable when its standard deviation (in scaled units: a
        fraction of the search half-range) exceeds this.
    coefficient_tol : float
        Coefficients below this fraction of the largest are left out of named combinations.
    """

    rtol: float = 1e-9
    weak: float = 1.0
    coefficient_tol: float = 0.05


@dataclass(frozen=True)
class Combination:
    """A direction in parameter space, in the user's names and units.

    ``coefficients[name]`` is how much the parameter changes (display units: m, deg, or plain)
    when moving one unit along the direction; the largest magnitude is 1.
    """

    coefficients: dict[str, float]
    units: dict[str, str]
    sigma: float  # standard deviation along the direction (scaled units); inf if unobservable

    @property
    def names(self) -> list[str]:
        return list(self.coefficients)

    def describe(self) -> str:
        """A sentence a user can act on."""
        items = list(self.coefficients.items())
        if len(items) == 1:
            name = items[0][0]
            return f"'{name}' cannot be determined: no measurement changes when it changes"
        parts = []
        for name, c in items:
            unit = self.units.get(name, "")
            parts.append(f"{name} by {c:+.3g}{(' ' + unit) if unit else ''}")
        moved = ", ".join(parts[:-1]) + " and " + parts[-1]
        if len(items) == 2:
            (a, ca), (b, cb) = items
            sign = "−" if ca * cb > 0 else "+"
            ratio = abs(ca / cb) if cb else float("inf")
            combo = f"{a} {sign} {ratio:.3g}·{b}" if abs(ratio - 1) > 1e-3 else f"{a} {sign} {b}"
            return (
                f"only one combination of '{a}' and '{b}' is observable: changing {moved} together leaves every "
                f"prediction unchanged, so {combo} cannot be determined"
            )
        return f"changing {moved} together leaves every prediction unchanged"

    def to_json(self) -> dict[str, Any]:
        return {
            "coefficients": self.coefficients,
            "units": self.units,
            "description": self.describe(),
        }


@dataclass
class Suggestion:
    """A candidate measurement and what it would bring."""

    record: dict[str, Any]
    rank_gain: int
    sigma_reduction: float  # relative reduction of the largest scaled σ (0..1)
    text: str

    def to_json(self) -> dict[str, Any]:
        return {
            "measurement": self.record,
            "rank_gain": self.rank_gain,
            "sigma_reduction": self.sigma_reduction,
            "description": self.text,
        }


@dataclass
class Observability:
    """Rank, condition, unobservable and weak directions, and the covariance of the unknowns."""

    names: list[str]
    units: dict[str, str]
    scales: np.ndarray
    singular_values: np.ndarray  # of the scaled measurement Jacobian
    rank: int
    rank_with_priors: int
    condition: float
    unobservable: list[Combination]
    weak: list[Combination]
    # SI units; inf rows/columns for unobservable unknowns: an np.ndarray, or for a large structured
    # problem a mbcal.structured.BlockCovariance (entries on request, never n × n)
    covariance: Any
    std: np.ndarray
    correlation: Any  # np.ndarray, or the BlockCovariance of the correlations
    chi2_scale: float = 1.0
    suggestions: list[Suggestion] = field(default_factory=list)
    null_space: np.ndarray | None = None  # (n, k) scaled
    n_values: int | None = None  # measured values (rows of the measurement Jacobian)
    active_bounds: dict[str, str] = field(default_factory=dict)  # unknown → "lower" | "upper", held fixed
    # The covariance's eigen-decomposition in scaled units (covariance / outer(scales, scales)):
    # (eigenvalues, eigenvectors as columns), set by :func:`analyze` when every unknown has a finite
    # σ — it is χ²·V diag(1/s²) Vᵀ from the SVD just taken, so the fit's weak directions need no
    # second decomposition (an 87 × 87 eigh: ~0.7 ms of a 13-view calibration, issue 16).
    scaled_eigen: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def n_free(self) -> int:
        """Unknowns not held at an active bound: what the rank is compared with."""
        return self.n - len(self.active_bounds)

    @property
    def fixed(self) -> np.ndarray:
        """(n,) bool: held at an active bound."""
        return np.array([name in self.active_bounds for name in self.names], dtype=bool)

    @property
    def observable(self) -> bool:
        """True when the measurements alone determine every unknown (those at an active bound
        are determined by it)."""
        return self.rank == self.n_free

    @property
    def observable_with_priors(self) -> bool:
        return self.rank_with_priors == self.n_free

    def verdict(self) -> str:
        free = self.n_free
        held = f" free ({len(self.active_bounds)} held at an active bound)" if self.active_bounds else ""
        if self.observable and free == 0:  # every unknown held: no matrix, no condition number (it read "inf")
            return f"observable: nothing left free ({len(self.active_bounds)} held at an active bound)"
        if self.observable:
            text = f"observable: rank {self.rank} of {free}{held}, condition number {self.condition:.3g}"
            if self.weak:
                text += f"; {len(self.weak)} weakly observable direction(s)"
            return text
        text = f"NOT observable: rank {self.rank} of {free}{held} ({free - self.rank} unobservable direction(s))"
        if self.n_values is not None and self.n_values < free:
            text += f"; underdetermined: {self.n_values} measured values for {free} unknowns"
        if self.observable_with_priors:
            text += "; the priors (sigma) make the estimate determined"
        return text


SCALE_SOURCES = ("range", "prior", "nominal")
"""What an unknown's natural scale is (:func:`scale_sources`): half its search range, its prior σ,
or max(1, |nominal|)."""


def scale_sources(params) -> np.ndarray:
    """(n,) int: which rule :func:`unknown_scales` applies to each unknown — an index into
    :data:`SCALE_SOURCES` (0 half the search range, 1 the prior σ, 2 max(1, |nominal|))."""
    lo, hi, sig = params.lower, params.upper, params.prior_sigma
    ranged = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
    return np.where(ranged, 0, np.where(np.isfinite(sig), 1, 2))


def unknown_scales(params) -> np.ndarray:
    """Each unknown's natural scale: half its search range, else its prior σ, else max(1, |nominal|).

    The one yardstick of "how well is it determined": the observability analysis calls a direction
    weakly observable, and the fit verdict (:mod:`mbcal.fit`) weakly determined, when σ along it
    exceeds one scale (half the search range, where there is one)."""
    lo, hi, sig, x0 = params.lower, params.upper, params.prior_sigma, params.x0
    source = scale_sources(params)
    with np.errstate(invalid="ignore"):
        return np.where(source == 0, (hi - lo) / 2.0, np.where(source == 1, sig, np.maximum(1.0, np.abs(x0))))


def scale_stand_ins(names: Sequence[str], params) -> list[str]:
    """For the unknowns among ``names`` that have no search range, their scale (what stands in for
    half a search range, :func:`unknown_scales`) in display units: ``"x: prior σ = 2 mm"``,
    ``"d: |nominal| = 5 m"``, ``"z: 1 m (|nominal| < 1)"``; empty when each has a search range."""
    index = {name: i for i, name in enumerate(params.names)}
    source, scale = scale_sources(params), unknown_scales(params)
    x0 = params.x0
    out = []
    for name in names:
        i = index.get(name)
        if i is None or source[i] == 0:
            continue
        unit = params.info(name).unit
        shown = f"{to_display(unit, float(scale[i])):.3g}{(' ' + unit) if unit else ''}"
        if source[i] == 1:
            out.append(f"{name}: prior σ = {shown}")
        elif abs(float(x0[i])) >= 1.0:
            out.append(f"{name}: |nominal| = {shown}")
        else:
            out.append(f"{name}: {shown} (|nominal| < 1)")
    return out


def yardstick_text(stand_ins: Sequence[str], count: int, *, half: bool) -> str:
    """What σ along a direction of ``count`` unknowns is measured in, ``stand_ins`` those without
    a search range (:func:`scale_stand_ins`): one scale, half the search range (``half``: the
    observability analysis's "14 × …"), or two, the whole range (the fit verdict's "707 % of …")."""
    listed = "; ".join(stand_ins)
    if not stand_ins:
        return "half the search range" if half else "the search range"
    if len(stand_ins) == count:
        return f"{'its scale' if half else 'its range, ± its scale'} (no search range; {listed})"
    if half:
        return f"its scale (half the search range; without one, {listed})"
    return f"its range (the search range; without one, ± its scale: {listed})"


def weak_scale_text(names: Sequence[str], params) -> str:
    """What σ along a weakly observable direction of ``names`` is measured in — each unknown's
    scale (:func:`unknown_scales`) — for "σ along this direction is 14 × …"."""
    stand_ins = scale_stand_ins(names, params) if params is not None else []
    return yardstick_text(stand_ins, len(names), half=True)


def _sparse_basis(N: np.ndarray) -> np.ndarray:
    """A basis of span(N) (n, k) with as many zeros as reduced row echelon form gives."""
    if N.shape[1] == 0:
        return N
    A = N.T.copy()  # (k, n)
    k, n = A.shape
    row = 0
    for col in range(n):
        if row >= k:
            break
        pivot = row + int(np.argmax(np.abs(A[row:, col])))
        if abs(A[pivot, col]) < 1e-10:
            continue
        A[[row, pivot]] = A[[pivot, row]]
        A[row] /= A[row, col]
        for r in range(k):
            if r != row:
                A[r] -= A[r, col] * A[row]
        row += 1
    A[np.abs(A) < 1e-12] = 0.0
    return A.T


def _combination(d_scaled: np.ndarray, names, units, scales, sigma: float, tol: float) -> Combination:
    d = d_scaled * scales  # SI change per unit along the direction
    shown = np.array([to_display(units.get(n, ""), v) for n, v in zip(names, d)])
    big = np.max(np.abs(shown)) if shown.size else 1.0
    big = big if big > 0 else 1.0
    coefficients = {}
    for n, v, ds in zip(names, shown / big, d_scaled / max(np.max(np.abs(d_scaled)), 1e-300)):
        if abs(ds) >= tol:
            coefficients[n] = float(v)
    return Combination(coefficients, {n: units.get(n, "") for n in coefficients}, sigma)


def _spectrum(J: np.ndarray, n: int, rtol: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Singular values (n,) padded with zeros, right singular vectors (n, n) as columns, and
    the mask of those above ``rtol · σ_max``."""
    if J.shape[0] == 0:
        return np.zeros(n), np.eye(n), np.zeros(n, dtype=bool)
    # Only V is needed: with at least n rows the thin SVD has all n right singular vectors and
    # skips U (m × m: the cost of the analysis for a tall Jacobian).  For m ≥ 2n LAPACK's gesdd
    # factors J = QR and takes the SVD of R, then forms the m × n U = Q·U_R that is thrown away
    # here: the SVD of R alone gives the same singular values and V, bit for bit, in less than
    # half the time (random dense J of 1,404 × 87: 17 → 7.7 ms; 20,000 × 609: 3.9 → 1.6 s, 2 cores).
    # The structured solver's analysis hands in an n × n R already and takes the other branch.
    m, k = J.shape
    if m >= 2 * k and k >= 16:
        _, sv, Vt = np.linalg.svd(np.linalg.qr(J, mode="r"))
    else:
        _, sv, Vt = np.linalg.svd(J, full_matrices=m < k)
    full = np.zeros(n)
    full[: len(sv)] = sv[:n]
    smax = full.max() if n else 0.0
    return full, Vt.T, (full > rtol * smax) if smax > 0 else np.zeros(n, dtype=bool)


def analyze(
    J_measurements: np.ndarray,
    J_priors: np.ndarray | None,
    names: Sequence[str],
    units: dict[str, str],
    scales: np.ndarray,
    *,
    config: ObservabilityConfig | None = None,
    chi2_scale: float = 1.0,
    active: np.ndarray | None = None,
) -> Observability:
    """Observability and covariance from whitened Jacobians.

    Parameters
    ----------
    J_measurements : (m, n)
        Whitened Jacobian of the measurements.
    J_priors : (p, n) or None
        Whitened Jacobian of the prior rows.
    names, units, scales
        The unknowns, their display units and natural scales.
    chi2_scale : float
        Multiply the covariance by this (the reduced χ², when asked to).
    active : (n,) int, optional
        The solver's active bounds (−1 lower, +1 upper, 0 free): those unknowns are held fixed
        (see the module's documentation).
    """
    if active is not None and np.any(np.asarray(active) != 0):
        return _held_at_bounds(J_measurements, J_priors, names, units, scales, config, chi2_scale, np.asarray(active))
    config = config or ObservabilityConfig()
    n = len(names)
    S = np.asarray(scales, dtype=float)
    Js = np.asarray(J_measurements, dtype=float) * S
    full_sv, V, observable_mask = _spectrum(Js, n, config.rtol)
    smax = full_sv.max() if n else 0.0
    rank = int(observable_mask.sum())
    condition = float(smax / full_sv[observable_mask].min()) if rank else float("inf")
    null = V[:, ~observable_mask]

    # The covariance uses the priors as well.
    Jt = Js if J_priors is None or len(J_priors) == 0 else np.vstack([Js, np.asarray(J_priors) * S])
    # Without priors Jt is Js: its spectrum is the one just computed (issue 15: one SVD, not two).
    svt_full, Vt_full, keep = (full_sv, V, observable_mask) if Jt is Js else _spectrum(Jt, n, config.rtol)
    rank_t = int(keep.sum())
    Vk = Vt_full[:, keep]
    cov_s = (Vk / svt_full[keep] ** 2) @ Vk.T * chi2_scale
    null_t = Vt_full[:, ~keep]
    in_null = np.sum(null_t**2, axis=1) > 1e-12 if null_t.size else np.zeros(n, dtype=bool)
    cov = cov_s * np.outer(S, S)
    cov[in_null, :] = np.inf
    cov[:, in_null] = np.inf
    std = np.sqrt(np.where(np.isfinite(np.diag(cov)), np.diag(cov), np.inf))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std, std)
    corr[~np.isfinite(corr)] = np.nan
    np.fill_diagonal(corr, np.where(np.isfinite(std), 1.0, np.nan))

    unobservable = [
        _combination(v, names, units, S, float("inf"), config.coefficient_tol) for v in _sparse_basis(null).T
    ]
    weak = []
    for i in np.nonzero(observable_mask)[0]:
        sigma_dir = 1.0 / full_sv[i] * np.sqrt(chi2_scale)
        if sigma_dir > config.weak:
            weak.append(_combination(V[:, i], names, units, S, float(sigma_dir), config.coefficient_tol))
    return Observability(
        names=list(names),
        units=units,
        scales=S,
        singular_values=full_sv,
        rank=rank,
        rank_with_priors=rank_t,
        condition=condition,
        unobservable=unobservable,
        weak=weak,
        covariance=cov,
        std=std,
        correlation=corr,
        chi2_scale=chi2_scale,
        null_space=null,
        n_values=int(np.asarray(J_measurements).shape[0]),
        scaled_eigen=None if np.any(in_null) else (svt_full[keep] ** -2.0 * chi2_scale, Vk),
    )


def _held_at_bounds(
    J_measurements: np.ndarray,
    J_priors: np.ndarray | None,
    names: Sequence[str],
    units: dict[str, str],
    scales: np.ndarray,
    config: ObservabilityConfig | None,
    chi2_scale: float,
    active: np.ndarray,
) -> Observability:
    """:func:`analyze` with the unknowns at active bounds held fixed: the analysis of the free
    columns, embedded back (σ 0, covariance rows and columns 0, correlations NaN)."""
    free = active == 0
    n = len(names)
    Jm = np.asarray(J_measurements, dtype=float)
    Jp = None if J_priors is None else np.asarray(J_priors, dtype=float)[:, free]
    inner = analyze(
        Jm[:, free],
        Jp,
        [name for name, f in zip(names, free) if f],
        units,
        np.asarray(scales, dtype=float)[free],
        config=config,
        chi2_scale=chi2_scale,
    )
    cov = np.zeros((n, n))
    cov[np.ix_(free, free)] = inner.covariance
    corr = np.full((n, n), np.nan)
    corr[np.ix_(free, free)] = inner.correlation
    std = np.zeros(n)
    std[free] = inner.std
    inner_null = inner.null_space if inner.null_space is not None else np.zeros((int(free.sum()), 0))
    null = np.zeros((n, inner_null.shape[1]))
    null[free] = inner_null
    return Observability(
        names=list(names),
        units=units,
        scales=np.asarray(scales, dtype=float),
        singular_values=inner.singular_values,
        rank=inner.rank,
        rank_with_priors=inner.rank_with_priors,
        condition=inner.condition,
        unobservable=inner.unobservable,
        weak=inner.weak,
        covariance=cov,
        std=std,
        correlation=corr,
        chi2_scale=chi2_scale,
        null_space=null,
        n_values=inner.n_values,
        active_bounds=active_sides(names, active),
    )


def active_sides(names: Sequence[str], active: np.ndarray) -> dict[str, str]:
    """{unknown: "lower" | "upper"} of the unknowns held at an active bound (``active``: −1, 0, +1)."""
    return {name: ("lower" if a < 0 else "upper") for name, a in zip(names, np.asarray(active).tolist()) if a != 0}


def rank_candidates(
    obs: Observability,
    J_measurements: np.ndarray,
    J_priors: np.ndarray | None,
    candidates: Sequence[tuple[dict[str, Any], np.ndarray]],
    *,
    top: int = 10,
) -> list[Suggestion]:
    """Rank candidate measurements by how much they raise the rank, then shrink the worst σ.

    ``candidates`` holds (record, whitened Jacobian rows (s, n)) pairs.
    """
    S = obs.scales
    if obs.active_bounds:
        S = np.where(obs.fixed, 0.0, S)  # held at a bound: no measurement can help
    Js = np.asarray(J_measurements) * S
    P = np.asarray(J_priors) * S if J_priors is not None and len(J_priors) else np.zeros((0, len(S)))
    # Rows with the information Jsᵀ Js + PᵀP (n of them: an R factor), kept as rows so that σ comes
    # from singular values, not from eigenvalues of the squared matrix (those lost ~1e-6 of σ at a
    # condition number of 1e5, more than most candidates change it).
    info_rows: Any = np.linalg.qr(np.vstack([Js, P]), mode="r")  # (numpy's stubs type it loosely)
    null = obs.null_space if obs.null_space is not None else np.zeros((len(S), 0))
    seen = []
    for record, rows in candidates:
        R = np.atleast_2d(rows) * S
        found = null_seen(R, R @ null, null)
        if found is not None:
            seen.append((*found, record, R))
    return best_suggestions(
        seen, _worst_sigma(info_rows, null), lambda R, new_null: _worst_sigma(np.vstack([info_rows, R]), new_null), top
    )


def null_seen(R: np.ndarray, R_null: np.ndarray, null: np.ndarray) -> tuple[int, np.ndarray] | None:
    """What a candidate's scaled rows ``R`` see of the null space ``null`` (n, k) (``R_null``: R
    times it): the rank they add and the null directions they leave unobservable; None when R
    has no finite nonzero entry.  (The scoring of :func:`rank_candidates`, dense or by blocks.)"""
    norm = np.linalg.norm(R)
    if not np.isfinite(norm) or norm == 0:
        return None
    gain = 0
    if null.shape[1]:
        sv = np.linalg.svd(R_null, compute_uv=False)
        gain = int(np.sum(sv > 1e-6 * norm))
    new_null = null
    if gain:
        # The directions of the null space the candidate does not see stay unobservable.
        _, sv2, vt = np.linalg.svd(R_null)
        seen = np.zeros(null.shape[1], dtype=bool)
        seen[: len(sv2)] = sv2 > 1e-6 * norm
        new_null = null @ vt.T[:, ~seen]
    return gain, new_null


def best_suggestions(
    seen: Sequence[tuple[int, np.ndarray, dict[str, Any], Any]],
    base_worst: float,
    worst: Callable[[Any, np.ndarray], float],
    top: int,
) -> list[Suggestion]:
    """The ``top`` candidates by rank gain, then by the relative reduction of the largest scaled σ
    (stable: ties keep the candidates' order), as suggestions with their text.  ``seen``: (rank
    gain, null directions left, record, rows) of each candidate (:func:`null_seen`); ``worst``:
    rows, null directions left → the largest σ with the candidate, asked only of candidates whose
    gain can reach the top (a candidate with less gain than the top-th largest cannot)."""
    if not seen:
        return []
    gains = sorted((gain for gain, *_ in seen), reverse=True)
    needed = gains[min(top, len(gains)) - 1]
    scored = []
    for gain, new_null, record, rows in seen:
        if gain >= needed:
            w = worst(rows, new_null)
            reduction = 0.0 if not np.isfinite(base_worst) or base_worst == 0 else max(0.0, 1.0 - w / base_worst)
            scored.append((gain, reduction, record))
    scored = sorted(scored, key=lambda t: (-t[0], -t[1]))
    out = []
    for gain, reduction, record in scored[:top]:
        what = ", ".join(f"{k} {v}" for k, v in record.items() if k not in ("kind", "sigma"))
        text = f"{record['kind']}: {what}"
        if gain:
            text += f" — raises the rank by {gain}"
        if reduction > 0:
            text += f" — largest σ −{100 * reduction:.0f} %"
        out.append(Suggestion(record, gain, reduction, text))
    return out


def _worst_sigma(rows: np.ndarray, null: np.ndarray) -> float:
    """The largest σ (scaled) over the observable subspace of the information matrix rowsᵀ rows:
    1 / the smallest singular value of the rows over the complement of ``null`` that exceeds
    1e-6 of the largest (an eigenvalue of the information above 1e-12 of the largest)."""
    n = rows.shape[1]
    if null.shape[1]:
        # Only the directions outside the unobservable ones: a basis of their complement.
        Q, _ = np.linalg.qr(null, mode="complete")
        rows = rows @ Q[:, null.shape[1] :]
    sv = np.linalg.svd(rows, compute_uv=False) if rows.size else np.zeros(0)
    positive = sv[sv > 1e-6 * max(sv.max(initial=0.0), 1e-300)]
    if positive.size == 0 or n == 0:
        return float("inf")
    return float(1.0 / positive.min())


@dataclass(frozen=True, slots=True)  # slots: a large calibration reports 100,000 of them (issue 15)
class PointUncertainty:
    """Uncertainty of a named point's position, split along and across a line of sight."""

    point: str
    configuration: str
    camera: str | None
    position: np.ndarray  # world (m)
    covariance: np.ndarray  # (3, 3) m²
    parallel: float  # σ along the line of sight (m)
    perpendicular: float  # largest σ across it (m)

    @property
    def total(self) -> float:
        return float(np.sqrt(np.trace(self.covariance))) if np.all(np.isfinite(self.covariance)) else float("inf")

    def to_json(self) -> dict[str, Any]:
        return {
            "point": self.point,
            "configuration": self.configuration,
            "camera": self.camera,
            "position": [float(v) for v in self.position],
            "sigma_parallel": _finite_or_none(self.parallel),
            "sigma_perpendicular": _finite_or_none(self.perpendicular),
            "sigma_total": _finite_or_none(self.total),
        }


T = TypeVar("T")


class MadeWhenRead(Sequence[T]):
    """A read-only list whose items are made from arrays when read (:meth:`_make`), for the
    many-row parts of a report (issues 15, 16): subclasses give ``__len__`` and ``_make``."""

    __slots__ = ()

    def _make(self, k: int) -> T:
        raise NotImplementedError

    @overload
    def __getitem__(self, i: int) -> T: ...

    @overload
    def __getitem__(self, i: slice) -> list[T]: ...

    def __getitem__(self, i: int | slice) -> T | list[T]:
        if isinstance(i, slice):
            return [self._make(k) for k in range(*i.indices(len(self)))]
        return self._make(range(len(self))[i])  # negative indices; IndexError past the end

    def __iter__(self) -> Iterator[T]:
        return (self._make(k) for k in range(len(self)))


class PointLabels(MadeWhenRead[tuple[str, str, "str | None"]]):
    """(point, configuration, camera) names of many points from index arrays (a camera index < 0:
    none), each tuple made when read (issue 16)."""

    __slots__ = ("_names", "_points", "_configs", "_config_names", "_cameras", "_camera_names")

    def __init__(self, point_names, points, config_names, configs, camera_names, cameras):
        self._names, self._points = point_names, points
        self._config_names, self._configs = config_names, configs
        self._camera_names, self._cameras = camera_names, cameras

    def __len__(self) -> int:
        return len(self._points)

    def _make(self, k: int) -> tuple[str, str, str | None]:
        cam = int(self._cameras[k])
        return (
            self._names[int(self._points[k])],
            self._config_names[int(self._configs[k])],
            self._camera_names[cam] if cam >= 0 else None,
        )


class PointUncertainties(MadeWhenRead[PointUncertainty]):
    """Many points' uncertainties as arrays: a list of :class:`PointUncertainty` to its readers,
    each made when it is read (issue 16: 702 objects were ~1.5 ms of a 13-view calibration;
    issue 15: 108,000 at 2,000 views).  ``positions`` (k, 3), ``covariances`` (k, 3, 3),
    ``parallel`` and ``perpendicular`` (k,) are the arrays."""

    __slots__ = ("items", "positions", "covariances", "parallel", "perpendicular")

    def __init__(self, items, positions, covariances, parallel, perpendicular):
        self.items: Sequence[tuple[str, str, str | None]] = items
        self.positions: np.ndarray = positions
        self.covariances: np.ndarray = covariances
        self.parallel: np.ndarray = parallel
        self.perpendicular: np.ndarray = perpendicular

    def __len__(self) -> int:
        return len(self.items)

    def _make(self, k: int) -> PointUncertainty:
        name, cfg, cam = self.items[k]
        return PointUncertainty(
            name,
            cfg,
            cam,
            self.positions[k],
            self.covariances[k],
            float(self.parallel[k]),
            float(self.perpendicular[k]),
        )


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def split_line_of_sight(cov: np.ndarray, position: np.ndarray, eye: np.ndarray | None) -> tuple[float, float]:
    """(σ∥, σ⟂max) of a 3×3 covariance relative to the line from ``eye`` to ``position``."""
    if not np.all(np.isfinite(cov)):
        return float("inf"), float("inf")
    if eye is None:
        w = np.linalg.eigvalsh(cov)
        return float("nan"), float(np.sqrt(max(w.max(), 0.0)))
    u = position - eye
    u = u / np.linalg.norm(u)
    par = float(np.sqrt(max(u @ cov @ u, 0.0)))
    P = np.eye(3) - np.outer(u, u)
    perp = float(np.sqrt(max(np.linalg.eigvalsh(P @ cov @ P).max(), 0.0)))
    return par, perp


def _largest_across(u: np.ndarray, C: np.ndarray) -> np.ndarray:
    """(k,) the largest eigenvalue of each covariance C (k, 3, 3) restricted to the plane across
    the unit vector u (k, 3): the 2 × 2 matrix B = EᵀCE in an orthonormal basis E of that plane,
    its larger eigenvalue (b₀₀ + b₁₁)/2 + hypot((b₀₀ − b₁₁)/2, b₀₁) in closed form (issue 16: the
    batched 3 × 3 eigvalsh of the projected matrix was 0.4 ms for 702 points)."""
    x, y, z = u[:, 0], u[:, 1], u[:, 2]
    # the first axis: u × (the coordinate axis least aligned with u), normalised
    j = np.argmin(np.abs(u), axis=1)
    zero = np.zeros_like(x)
    e1 = np.where(
        (j == 0)[:, None],
        np.stack([zero, z, -y], axis=1),
        np.where((j == 1)[:, None], np.stack([-z, zero, x], axis=1), np.stack([y, -x, zero], axis=1)),
    )
    e1 /= np.sqrt(np.sum(e1 * e1, axis=1))[:, None]
    E = np.stack([e1, np.cross(u, e1)], axis=2)  # (k, 3, 2)
    B = np.swapaxes(E, 1, 2) @ C @ E
    return 0.5 * (B[:, 0, 0] + B[:, 1, 1]) + np.hypot(0.5 * (B[:, 0, 0] - B[:, 1, 1]), B[:, 0, 1])


def point_uncertainty(
    name: str,
    configuration: str,
    camera: str | None,
    position: np.ndarray,
    J_point: np.ndarray,
    covariance: np.ndarray,
    eye: np.ndarray | None,
) -> PointUncertainty:
    """Propagate the unknowns' covariance to a point (J_point: (3, n) ∂p/∂x)."""
    used = np.any(J_point != 0, axis=0)
    if np.any(~np.isfinite(covariance[np.ix_(used, used)])):
        cov = np.full((3, 3), np.inf)
    else:
        Ju = J_point[:, used]
        cov = Ju @ covariance[np.ix_(used, used)] @ Ju.T
    par, perp = split_line_of_sight(cov, position, eye)
    return PointUncertainty(name, configuration, camera, position, cov, par, perp)


def _equal_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows (k, n) of booleans grouped when equal: an order of the rows in which equal ones are
    adjacent, and where each group starts in it.  The rows packed into 64-bit words and sorted
    by them (np.unique(axis=0) took 7 ms for 702 rows of 87)."""
    packed = np.packbits(rows, axis=1)
    packed = np.pad(packed, ((0, 0), (0, -packed.shape[1] % 8)))
    words = np.ascontiguousarray(packed).view(np.uint64)  # (k, W)
    order = np.lexsort(words.T[::-1])
    ordered = words[order]
    new = np.ones(len(order), dtype=bool)
    new[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    return order, np.nonzero(new)[0]


def point_uncertainties(
    points: Sequence[tuple[str, str, str | None]],
    positions: np.ndarray,
    J_points: np.ndarray | None,
    covariance: np.ndarray | None,
    eyes: Sequence[np.ndarray | None] | np.ndarray,
    *,
    covariances: np.ndarray | None = None,
) -> Sequence[PointUncertainty]:
    """:func:`point_uncertainty` for many points at once: ``points`` (name, configuration, camera),
    positions (k, 3), Jacobians (k, 3, n), eyes (k entries, None: no line of sight; or a (k, 3)
    array with NaN rows for none).
    ``covariances`` (k, 3, 3): the points' covariances already propagated (a structured problem's,
    issue 15); then ``J_points`` and ``covariance`` are not used.

    Points whose Jacobians use the same unknowns are propagated together (one batched product
    per pattern, e.g. per view of a target), and the line-of-sight split is batched too."""
    k = len(points)
    if k == 0:
        return PointUncertainties([], np.empty((0, 3)), np.empty((0, 3, 3)), np.empty(0), np.empty(0))
    P = np.asarray(positions, dtype=float)
    covs = np.empty((k, 3, 3)) if covariances is None else np.asarray(covariances, dtype=float)
    if covariances is None:
        assert covariance is not None and J_points is not None
        J = np.asarray(J_points, dtype=float)
        used = np.any(J != 0, axis=1)  # (k, n)
        order, starts = _equal_rows(used)
        for idx in np.split(order, starts[1:]):
            mask = used[idx[0]]
            block = covariance[np.ix_(mask, mask)]
            if not np.all(np.isfinite(block)):
                covs[idx] = np.inf
            else:
                Ju = J[idx][:, :, mask]
                covs[idx] = Ju @ block @ np.swapaxes(Ju, 1, 2)
    par = np.full(k, np.inf)
    perp = np.full(k, np.inf)
    finite = np.all(np.isfinite(covs), axis=(1, 2))
    if isinstance(eyes, np.ndarray):
        eye_rows = np.asarray(eyes, dtype=float).reshape(k, 3)
        has_eye = np.all(np.isfinite(eye_rows), axis=1)
    else:
        has_eye = np.array([e is not None for e in eyes], dtype=bool)
        eye_rows = np.full((k, 3), np.nan)
        if has_eye.any():
            eye_rows[has_eye] = np.stack([np.asarray(e, dtype=float) for e in eyes if e is not None])
    plain = finite & ~has_eye
    if plain.any():
        par[plain] = np.nan
        perp[plain] = np.sqrt(np.maximum(np.linalg.eigvalsh(covs[plain]).max(axis=1), 0.0))
    sight = finite & has_eye
    if sight.any():
        u = P[sight] - eye_rows[sight]
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        C = covs[sight]
        along = np.einsum("ki,kij,kj->k", u, C, u)
        par[sight] = np.sqrt(np.maximum(along, 0.0))
        perp[sight] = np.sqrt(np.maximum(_largest_across(u, C), 0.0))
    return PointUncertainties(points, P, covs, par, perp)
