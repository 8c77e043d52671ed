"""The verdict on a calibration: is the fit consistent with the stated σ, and is every unknown well
determined?  (docs/report.md, "The fit verdict".)

**The χ² test.**  With the σ the measurements state, the whitened residuals of a correct model
are standard normal, so at the estimate S = Σ r² (measurement and prior rows) follows the χ²
distribution with m − n degrees of freedom (m residual rows, n the rank).  The fit is
*inconsistent* when the upper tail probability p = P(χ² ≥ S) is below the threshold
(:data:`DEFAULT_THRESHOLD`, 0.001): at that threshold a correct model and correct σ raise a false
alarm once in a thousand solves.  A fit better than expected (small S) is not an error.

**What to suspect** when it is inconsistent, worst first (by how much of S each explains), all
found on the problem linearised at the estimate, where setting measurements aside and refitting
is exact linear algebra:

- *outlying measurements*: how much S drops when a measurement is deleted and the rest refitted
  (its externally studentised residual) is tested against χ² with its number of values,
  Bonferroni-corrected for the number of measurements, relative to a robust (median) estimate
  of the noise level so that σ set uniformly too small does not make every measurement an
  outlier; the worst significant one is set aside (a tenth of them per round when there are
  many) and the search repeated until none is significant.  When they explain the excess, the
  report recommends a robust loss.
- *a structural error of the model*: the measurements are grouped by the frame (and its
  enclosing frames) of what they measure, by sensor and by configuration; a group whose
  measurements together are too large for the rest of the fit (a block deletion test,
  Bonferroni-corrected for the number of groups), or of which most measurements came out as
  outliers, is named: its object's dimensions or pose, or the sensor, are suspect.
- *σ set too small*: what remains is uniformly too large; the factor is √(S/dof) of the rest.

**Systematic residuals** (:func:`systematic_residuals`), tested whatever the χ² test says: a
camera whose neighbouring image points are off alike (or 3-D points, alike in space) — a model
error that stays within a σ stated larger than the real noise, which the χ² test cannot see —
makes the result untrustworthy.

With a robust loss the outliers it down-weights are expected: the test then applies to the
measurements left after setting the outliers aside.

**Weak determination.**  Each unknown is measured by its natural scale
(:func:`mbcal.observability.unknown_scales`: half its search range; without one its prior σ, else
max(1, |nominal|)) — the one yardstick the observability analysis uses too.  A direction whose σ,
priors included, exceeds :data:`DEFAULT_WEAK_FRACTION` (half) of its range (twice the scale: the
search range, or ± the scale of an unknown without one) — the measurements do not narrow what the
model says the value could be: the observability analysis's "weakly observable" — or a condition
number above :data:`DEFAULT_MAX_CONDITION` makes the result untrustworthy too.  Unknowns without a
search range are tested as well: a distance known to within ± 70 m when its nominal value is 5 m
is not "well determined".

**Another solution as good** (:func:`distinct_minima`).  Restarts that converged elsewhere with
S within :data:`AMBIGUOUS_MARGIN` of the best — χ²'s 95 % point for one degree of freedom: the data
do not prefer the best — at unknowns more than :data:`AMBIGUOUS_SIGMAS` σ from it (two mirror
poses, an angle whose sign the measurements cannot tell) make the result untrustworthy: the
estimate's σ describes one of the solutions and says nothing of the other.

**Untested measurements.**  A measurement that alone determines part of the
unknowns (deleting it loses rank: an eigenvalue of 1 in its block of the hat matrix) has a residual
of ~0 whatever its error; the report names it, and the verdict says so beside "consistent".

**Held at a hard limit.**  An unknown the data push past its ``bounded`` range ends on the limit
with σ 0: that is the limit, not a measurement of it, so the result is not trustworthy either
(``accept`` accepts it).

**Unobservable.**  When the measurements and priors together leave a direction undetermined
(rank below the number of free unknowns: σ = ∞), the verdict says so — "not observable", never
"well determined" — and ``accept`` does not override it: there is no estimate to accept.

``accept`` (``--accept-poor-fit``) keeps the verdict in the report but lets the result count as
usable: for scripts that want the estimate anyway.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal.measurements.registry import get_model
from mbcal.observability import Observability, ObservabilityConfig, scale_stand_ins, yardstick_text
from mbcal.problem import Problem, RowBlocks, blocks_by_size
from mbcal.solver import Status, represented_after
from mbcal.text import fmt
from mbcal.units import to_display


def _special() -> Any:
    """``scipy.special``, imported when first needed: ~0.2 s of start-up (its array-API
    machinery), which a consistent fit's single p-value does not need (issue 16)."""
    from scipy import special

    return special


def _upper_gamma(a: float, x: float) -> float:
    """Q(a, x) = Γ(a, x) / Γ(a), the regularised upper incomplete gamma function, for one a > 0
    and x ≥ 0: the power series of P = 1 − Q below x = a + 1, the continued fraction of Q above
    (evaluated by the modified Lentz method), each to double precision (Press et al., *Numerical
    Recipes*, 3rd ed., §6.2).  The prefactor xᵃe⁻ˣ/Γ(a) is taken in logarithms."""
    if math.isnan(x) or math.isnan(a):
        return math.nan  # as scipy: no verdict from a cost that is not a number
    if x <= 0.0:
        return 1.0
    if math.isinf(x):
        return 0.0
    if a < 10.0:
        log_front = a * math.log(x) - x - math.lgamma(a)
    else:  # the same without cancelling terms of size a (Stirling's series for log Γ(a), t = x/a − 1)
        t = (x - a) / a
        stirling = 1.0 / (12.0 * a) - 1.0 / (360.0 * a**3) + 1.0 / (1260.0 * a**5) - 1.0 / (1680.0 * a**7)
        # a·ln(x/a) − (x − a): by log1p near x = a, where the two terms cancel; directly elsewhere
        # (x far below a: t rounds to −1)
        exponent = -a * (t - math.log1p(t)) if abs(t) < 0.5 else a * (math.log(x) - math.log(a)) - (x - a)
        log_front = exponent + 0.5 * math.log(a / (2.0 * math.pi)) - stirling
    if x < a + 1.0:
        term = total = 1.0 / a
        n = 0
        while abs(term) > abs(total) * 1e-17 and n < 1_000_000:
            n += 1
            term *= x / (a + n)
            total += term
        return max(0.0, 1.0 - total * math.exp(log_front))
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 1_000_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        step = d * c
        h *= step
        if abs(step - 1.0) < 1e-16:
            break
    return math.exp(log_front) * h


def chi2_sf(x: float, df: float) -> float:
    """P(χ²_df ≥ x): the tail every consistency test of mbcal reads (the fit verdict's, the scan
    manager's test of an update against its prior)."""
    return float(_Chi2.sf(float(x), float(df)))


class _Chi2:
    """The χ² distribution's upper tail, its logarithm and median, as ``scipy.stats.chi2`` computes
    them (chdtrc; log of it; 2·P⁻¹(df/2, ½)): one tail in plain Python (:func:`_upper_gamma`),
    arrays of them from ``scipy.special`` (imported then)."""

    @staticmethod
    def sf(x: Any, df: Any) -> Any:
        if np.ndim(x) == 0 and np.ndim(df) == 0:
            return _upper_gamma(float(df) / 2.0, max(float(x), 0.0) / 2.0)
        return _special().chdtrc(df, np.maximum(x, 0.0))  # 1 below the support, as scipy.stats

    @staticmethod
    def logsf(x: Any, df: Any) -> Any:
        with np.errstate(divide="ignore"):
            return np.log(_Chi2.sf(x, df))

    @staticmethod
    def median(df: Any) -> Any:
        return 2.0 * _special().gammaincinv(np.asarray(df) / 2.0, 0.5)


class stats:  # noqa: N801  - reads like the module it stands for: stats.chi2.sf(...)
    chi2 = _Chi2


__all__ = [
    "DEFAULT_MAX_CONDITION",
    "DEFAULT_THRESHOLD",
    "DEFAULT_WEAK_FRACTION",
    "TOO_SMALL_REDUCED_CHI2",
    "FitConfig",
    "FitVerdict",
    "Suspect",
    "WeakDirection",
    "assess_fit",
    "assess_plan",
    "distinct_minima",
    "measurement_groups",
    "chi2_sf",
    "systematic_residuals",
]

DEFAULT_THRESHOLD = 1e-3
"""p-value below which a fit is inconsistent with the stated σ (and a suspect is significant)."""

DEFAULT_WEAK_FRACTION = 0.5
"""A direction of the unknowns is weakly determined when its σ exceeds this fraction of its range:
twice each unknown's scale (:func:`mbcal.observability.unknown_scales`) — the search range
(upper − lower), or for an unknown without one ± its prior σ, else ± max(1, |nominal|).  Half the
range is one scale: the limit by which the observability analysis calls a direction weakly
observable."""

DEFAULT_MAX_CONDITION = 1e10
"""Condition number (of the Jacobian scaled by the search half-ranges, priors included) above
which the estimate is numerically fragile: its σ differ by more than ten orders of magnitude."""

MIN_GROUP = 3
"""A group needs at least this many measurements to be named as a structural error."""

SYSTEMATIC_NEIGHBOURS = 4
"""Each image point is compared with this many nearest points of the same camera and view."""

SYSTEMATIC_MIN_CORRELATION = 0.25
"""Systematic residuals are named when neighbouring image points' residuals correlate at least
this much (a quarter of their scatter shared), significantly (the fit's threshold) …"""

SYSTEMATIC_MIN_SIZE = 0.1
"""… and the shared part is at least this fraction of σ (not a numerical ripple of a fit to
noise-free data)."""

UNTESTED_LEVERAGE = 0.99
"""A measurement is named untested when one of its directions has a leverage (an eigenvalue of
its block of the hat matrix) above this: an error along it leaves at most 1 % of itself in the
residual, so it must be 10× larger than elsewhere to be seen."""

HELD_Z = 3.090232306167813
"""An unknown held at a hard limit makes the result untrustworthy when the fit without the limit
would put it beyond by more than this many of its σ (the normal's one-sided point at the default
threshold, 0.001): nearer, the limit and the data agree within the noise — a gap whose true value
is 0 lands on its limit [0, ∞) half the time."""

TOO_SMALL_REDUCED_CHI2 = 0.1
"""Residuals far below the stated σ (:attr:`FitVerdict.sigma_too_large`): S / dof below this (the
scatter under ⅓ of σ) and the χ² lower tail P(χ²_dof ≤ S) below the verdict's threshold.  The
range fit's test (:mod:`mbcal.range.fit`), where it fails the fit; here it is a note."""

AMBIGUOUS_MARGIN = 3.841
"""Restarts that converged with S at most this much above the best one (χ²'s 95 % point for one
degree of freedom, in the units of the stated σ, or of the scaled covariance's) fit as well …"""

AMBIGUOUS_SIGMAS = 5.0
"""… and when one of them lies more than this many σ of the estimate from it in some unknown, the
measurements have more than one answer (:func:`distinct_minima`)."""

_ANGLE_UNITS = ("deg", "rad")  # unknowns whose values 2π apart are compared as the same angle

_RTOL = 1e-10  # singular values below this fraction of the largest count as zero
_MAX_ROUNDS = 200  # rounds of the outlier search (each refits the linearised problem once)


@dataclass(frozen=True)
class FitConfig:
    """Thresholds of the fit verdict (defaults documented in docs/report.md).

    Attributes
    ----------
    threshold : float
        Significance level: the fit is inconsistent when P(χ² ≥ S) < threshold; suspects are
        named at the same level (Bonferroni-corrected).
    weak_fraction : float
        A direction of the unknowns is weakly determined when its σ exceeds this fraction of its
        range (the search range; without one, ± the unknown's scale: see
        :data:`DEFAULT_WEAK_FRACTION`).
    max_condition : float
        Condition number above which the estimate counts as weakly determined.
    min_group : int
        Smallest group of measurements that can be named as a structural error.
    """

    threshold: float = DEFAULT_THRESHOLD
    weak_fraction: float = DEFAULT_WEAK_FRACTION
    max_condition: float = DEFAULT_MAX_CONDITION
    min_group: int = MIN_GROUP

    def __post_init__(self) -> None:
        if not 0 < self.threshold < 1:
            raise ValueError(f"the fit threshold must lie between 0 and 1, got {self.threshold}")
        if not self.weak_fraction > 0:
            raise ValueError(f"weak_fraction must be positive, got {self.weak_fraction}")
        if not self.max_condition > 1:
            raise ValueError(f"max_condition must exceed 1, got {self.max_condition}")


@dataclass(frozen=True)
class Suspect:
    """One explanation of an inconsistent fit.

    ``kind``: ``outliers`` (``ids`` are the measurements, worst first), ``structural`` (``subject``
    names the frame, sensor or configuration, ``ids`` its measurements) or ``sigma`` (``factor``:
    how much larger the residuals are than the stated σ).  ``excess`` is the part of S it explains.
    """

    kind: str
    subject: str
    ids: tuple[str, ...]
    excess: float
    p_value: float | None
    factor: float | None
    description: str

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "subject": self.subject,
            "ids": list(self.ids),
            "excess_chi2": _num(self.excess),
            "p_value": _num(self.p_value),
            "factor": _num(self.factor),
            "description": self.description,
        }


@dataclass(frozen=True)
class WeakDirection:
    """A poorly determined direction: its parameters (largest share first) and σ along it as a
    fraction of their ranges (the search range; without one, ± the unknown's scale, named in
    ``stand_ins``: :func:`mbcal.observability.scale_stand_ins`)."""

    names: tuple[str, ...]
    sigma: float
    stand_ins: tuple[str, ...] = ()

    def range_text(self) -> str:
        """What ``sigma`` is a fraction of, for "σ along this direction is 707 % of …"."""
        return yardstick_text(self.stand_ins, len(self.names), half=False)

    def to_json(self) -> dict[str, Any]:
        return {"names": list(self.names), "sigma_fraction": _num(self.sigma)}


@dataclass(frozen=True)
class FitVerdict:
    """Whether a calibration (or a plan) can be trusted beyond convergence and observability."""

    chi2: float | None
    """S = Σ r² at the estimate with the stated σ (plain squares even with a robust loss);
    None for a plan."""
    dof: int
    """Degrees of freedom m − n of the test (m rows, n the rank)."""
    p_value: float | None
    """P(χ²_dof ≥ S); None when not tested (a plan, or no redundancy)."""
    threshold: float
    consistent: bool
    suspects: tuple[Suspect, ...] = ()
    set_aside: tuple[str, ...] = ()
    """With a robust loss: the outliers left out of the test."""
    loss: str = "linear"
    weak: tuple[WeakDirection, ...] = ()
    weak_fraction: float = DEFAULT_WEAK_FRACTION
    condition: float = 1.0
    """Condition number of the covariance over the unknowns with a finite σ, in their scales; inf
    when no free unknown has one (an unobservable problem)."""
    max_condition: float = DEFAULT_MAX_CONDITION
    accepted: bool = False
    notes: tuple[str, ...] = field(default=())
    determined: bool = True
    """Every free unknown determined by the measurements and priors together (the observability
    analysis's ``observable_with_priors``): False when a direction has σ = ∞."""
    rank: int | None = None
    """Rank of the problem, priors included (None: not recorded)."""
    unknowns: int | None = None
    """Free unknowns (not held at an active bound) that the rank is compared with."""
    not_converged: str | None = None
    """Why the solve's best restart did not converge (its status: ``max_iterations``), else None:
    the verdict is then not trustworthy, and ``--accept-poor-fit`` does not accept it."""
    invalid_estimate: str | None = None
    """The estimate breaks a rule of the model (``file:line:col: message``: a focal length or a
    shape's size not positive — a search range that includes them lets a fit find a mirror camera,
    f < 0, that fits as well), else None: not trustworthy, and ``--accept-poor-fit`` does not
    accept it (a model written from it would not load)."""
    ambiguous: tuple[Suspect, ...] = ()
    """Another solution the restarts found, as good as the estimate and far from it
    (:func:`distinct_minima`, kind ``ambiguous``): not trustworthy, ``--accept-poor-fit`` accepts it."""
    untested: tuple[str, ...] = ()
    """Measurements (ids) that alone, or nearly alone, determine part of the unknowns (a leverage
    above :data:`UNTESTED_LEVERAGE`): the part of their error that moves those unknowns leaves
    (almost) no residual, so no test can see a mistake there (the tip of a lever whose two
    coordinates fix its angle and length).  Said beside the verdict;
    like a fit without redundancy, it does not make the result untrustworthy (a problem solved by
    blocks: the measurements of configurations with few rows, at most twice their unknowns)."""
    held: tuple[str, ...] = ()
    """Unknowns held at a hard limit the data push past significantly (the fit without the limit
    beyond it by more than :data:`HELD_Z` σ; σ 0 is the limit's, not a measurement of it): not
    trustworthy, ``--accept-poor-fit`` accepts it.  Nearer the limit: a note."""
    sigma_too_large: bool = False
    """The residuals are far below the stated σ (S / dof < :data:`TOO_SMALL_REDUCED_CHI2` and
    P(χ²_dof ≤ S) < the threshold): σ stated too large (a value in mm read as m, a detector's
    default) — the estimates' σ are then too large, and a model error within σ passes the χ² test.
    A note beside the verdict (simulated data without noise gives it too), not a reason for exit 1."""
    chi2_scaled: bool = False
    """The covariance was scaled by the reduced χ² (``scale_covariance``)."""
    systematic: tuple[Suspect, ...] = ()
    """Cameras whose image points' residuals are smooth across the image, or sets of 3-D points
    whose residuals are smooth in space (neighbouring points off alike): a model error the χ² test
    misses when σ is stated larger than the residuals (:func:`systematic_residuals`); not
    trustworthy, ``--accept-poor-fit`` accepts it."""

    @property
    def tested(self) -> bool:
        return self.p_value is not None

    @property
    def well_determined(self) -> bool:
        """Every unknown determined, no weak direction, the condition number in bounds."""
        return self.determined and not self.weak and not self.condition > self.max_condition

    @property
    def trustworthy(self) -> bool:
        """Converged, consistent and well determined (what ``accepted`` overrides, unless
        undetermined or not converged)."""
        return (
            self.not_converged is None
            and self.invalid_estimate is None
            and self.consistent
            and not self.systematic
            and not self.ambiguous
            and not self.held
            and self.well_determined
        )

    @property
    def ok(self) -> bool:
        """Trustworthy, or accepted — an unobservable problem is never ok (it has no estimate), nor
        one whose solve did not converge (it has no minimum)."""
        return self.trustworthy or (
            self.accepted and self.determined and self.not_converged is None and self.invalid_estimate is None
        )

    def _undetermined_text(self) -> str:
        if self.rank is None or self.unknowns is None:
            return "not observable"
        return f"not observable (rank {self.rank} of {self.unknowns})"

    @property
    def recommend_robust(self) -> bool:
        """Outliers explain the inconsistency (nothing structural, σ fine): use a robust loss."""
        kinds = {s.kind for s in self.suspects}
        return self.loss == "linear" and kinds == {"outliers"}

    def headline(self) -> str:
        """One line: consistent or not, with S, dof and p."""
        if self.chi2 is None:
            return "no measured values: the fit is not tested"
        aside = f" after setting aside {len(self.set_aside)} outlier(s)" if self.set_aside else ""
        if self.p_value is None:
            structural = sum(1 for s in self.suspects if s.kind == "structural")
            if structural and not self.consistent:
                # a robust fit: the groups were found off by tests of their own; nothing is left to test the rest
                return (
                    f"INCONSISTENT with the stated σ: {structural} group(s) systematically off (suspects below); "
                    f"the rest{aside} has no redundancy to test (S = {self.chi2:.6g}, 0 degrees of freedom)"
                )
            return f"S = {self.chi2:.6g} with no redundancy{aside} (0 degrees of freedom): the fit cannot be tested"
        what = "consistent with the stated σ" if self.consistent else "INCONSISTENT with the stated σ"
        rel = "≥" if self.p_value >= self.threshold else "<"
        shown = f"{self.p_value:.3g}" if self.p_value > 0 else "0 (below 1e-300)"
        test = f"S = {self.chi2:.6g} for {self.dof} degrees of freedom, p = {shown} {rel} {self.threshold:g}"
        groups = [s.subject for s in self.suspects if s.kind == "structural"]
        if groups and self.loss != "linear" and not self.consistent:
            # a robust fit tests the rest without the groups found off: S and p are the rest's (a
            # passing p beside "INCONSISTENT" read as a contradiction, and the groups were unnamed)
            named = ", ".join(groups[:3]) + (f" and {len(groups) - 3} more" if len(groups) > 3 else "")
            verdict = "passes" if self.p_value >= self.threshold else "fails too"
            outliers = f" and {len(self.set_aside)} outlier(s)" if self.set_aside else ""
            return (
                f"{what}: {len(groups)} group(s) systematically off ({named}; suspects below); the rest, without "
                f"them{outliers}, {verdict}: {test}"
            )
        return f"{what}{aside}: {test}"

    def lines(self) -> list[str]:
        """The verdict as report lines."""
        out = [f"fit: {self.headline()}"] if self.chi2 is not None else []
        if self.suspects:
            out.append("  suspects, worst first:")
            for k, s in enumerate(self.suspects, 1):
                out.append(f"    {k}. {s.description}")
            if self.recommend_robust:
                out.append(
                    "  recommendation: the outliers explain it; solve with a robust loss (--loss huber or cauchy, "
                    "CalibrateOptions(config=SolverConfig(loss='huber'))) or remove them"
                )
        if self.invalid_estimate is not None:
            out.append(
                f"  the estimate breaks the model: {self.invalid_estimate} — a search range that allows it let the "
                "fit find it (limits [lo, hi] on the parameter keep it valid: a focal length limits [1, 1e6]); a model "
                "written from it would not load"
            )
        for sy in self.systematic:
            out.append(f"  systematic residuals: {sy.description}")
        for other in self.ambiguous:
            out.append(f"  another solution as good: {other.description}")
        if self.untested:
            more = len(self.untested) - 10
            shown = ", ".join(self.untested[:10]) + (f" and {more} more" if more > 0 else "")
            out.append(
                f"  untested: {shown} — each alone (or nearly alone: leverage ≥ {UNTESTED_LEVERAGE:g}) determines "
                "part of the unknowns: the part of its error that moves them leaves (almost) no residual, so no test "
                "can see a mistake there (measure more of what it measures)"
            )
        if self.held:
            out.append(
                f"  held at a hard limit: {', '.join(self.held)} — the data put "
                f"{'it' if len(self.held) == 1 else 'them'} beyond the limit by more than {HELD_Z:.3g} σ, so σ 0 "
                "there is the limit's, not a measurement's (widen the limit, or check the model and the data)"
            )
        if not self.determined:
            missing = (
                f"{self.unknowns - self.rank} direction(s)"
                if self.rank is not None and self.unknowns is not None
                else "some directions"
            )
            out.append(
                f"  {self._undetermined_text()}: {missing} of the unknowns neither the measurements nor the priors "
                "determine (σ = ∞; see the observability section)"
            )
        for w in self.weak:
            out.append(
                f"  weakly determined ({', '.join(w.names)}): σ along this direction is {100 * w.sigma:.3g} % of "
                f"{w.range_text()} (threshold {100 * self.weak_fraction:g} %)"
            )
        if math.isfinite(self.condition) and self.condition > self.max_condition:
            out.append(
                f"  ill-conditioned: condition number {self.condition:.3g} above {self.max_condition:.3g} "
                "(the estimate is numerically fragile)"
            )
        if self.sigma_too_large:
            reduced = self.chi2 / self.dof if self.chi2 is not None and self.dof else float("nan")
            effect = (
                "the estimates' σ are scaled by the residuals (scale_covariance)"
                if self.chi2_scaled
                else f"the estimates' σ above are then ~{1 / math.sqrt(max(reduced, 1e-300)):.3g}× too large "
                "(--scale-covariance scales them by the residuals)"
            )
            out.append(
                f"  residuals far below σ: reduced χ² = {reduced:.3g} (< {TOO_SMALL_REDUCED_CHI2:g}, and "
                f"P(χ² ≤ S) < {self.threshold:g}): σ stated too large? {effect}; a model error within σ passes the "
                "χ² test (data simulated without noise give this too)"
            )
        out.extend(f"  {note}" for note in self.notes)
        out.append(f"verdict: {self.verdict()}")
        return out

    def verdict(self) -> str:
        """One phrase: trustworthy or not, and why."""
        if self.trustworthy:
            if self.tested:
                if self.untested:
                    return f"consistent and well determined, but {len(self.untested)} measurement(s) untested (above)"
                return "consistent and well determined"
            # a plan (no measured values) has no fit to test; a solve without redundancy has one it cannot test
            return "well determined" if self.chi2 is None else "well determined (the fit is not tested)"
        why = []
        if self.not_converged is not None:
            why.append(f"the solve did not converge ({self.not_converged})")
        if self.invalid_estimate is not None:
            why.append("the estimate breaks the model")
        if not self.determined:
            why.append(self._undetermined_text())
        if not self.consistent:
            why.append("the fit is inconsistent with the stated σ")
        if self.systematic:
            why.append("the residuals are systematic")
        if self.ambiguous:
            why.append("another solution fits as well")
        if self.held:
            why.append(f"{'an unknown is' if len(self.held) == 1 else 'unknowns are'} held at a hard limit")
        if self.determined and not self.well_determined:
            why.append("weakly determined")
        text = f"NOT trustworthy: {' and '.join(why)}"
        if not self.determined:  # nothing to accept: --accept-poor-fit does not make it usable
            return text + " (exit status 1, even with --accept-poor-fit: add measurements or fix unknowns)"
        if self.not_converged is not None:  # no minimum to accept
            return text + " (exit status 1, even with --accept-poor-fit: more iterations or other starts)"
        if self.invalid_estimate is not None:  # not a model at all
            return text + " (exit status 1, even with --accept-poor-fit: limit the parameter to valid values)"
        if self.accepted:
            return text + "; accepted anyway (--accept-poor-fit)"
        return text + " (exit status 1; --accept-poor-fit accepts it)"

    def text(self) -> str:
        return "\n".join(self.lines())

    def to_json(self) -> dict[str, Any]:
        return {
            "chi2": _num(self.chi2),
            "dof": self.dof,
            "p_value": _num(self.p_value),
            "threshold": self.threshold,
            "tested": self.tested,
            "consistent": self.consistent,
            "loss": self.loss,
            "set_aside": list(self.set_aside),
            "suspects": [s.to_json() for s in self.suspects],
            "systematic": [s.to_json() for s in self.systematic],
            "ambiguous": [s.to_json() for s in self.ambiguous],
            "untested": list(self.untested),
            "held": list(self.held),
            "sigma_too_large": self.sigma_too_large,
            "notes": list(self.notes),
            "recommend_robust": self.recommend_robust,
            "weak": [w.to_json() for w in self.weak],
            "weak_fraction": self.weak_fraction,
            "condition_number": _num(self.condition),
            "max_condition": self.max_condition,
            "well_determined": self.well_determined,
            "accepted": self.accepted,
            "not_converged": self.not_converged,
            "invalid_estimate": self.invalid_estimate,
            "ok": self.ok,
            "verdict": self.verdict(),
        }


def _num(v: float | None) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


# ---- groups of measurements --------------------------------------------------------------------------


def measurement_groups(problem: Problem) -> dict[str, list[int]]:
    """Measurements grouped by what they share: the frame of each point, shape or frame they refer
    to and the frames enclosing it (``frame room.box``), each sensor (``camera eyes.left``), and
    each configuration when there are several.  Groups that hold every measurement are left out
    (nothing to compare them with)."""
    model = problem.model
    ms = problem.measurements.measurements
    groups: dict[str, list[int]] = {}

    def add(label: str, i: int) -> None:
        members = groups.setdefault(label, [])
        if not members or members[-1] != i:
            members.append(i)

    def add_frame(frame: int, i: int) -> None:
        while frame >= 0:
            add(f"{model.frames[frame].keyword} {model.frames[frame].name}", i)
            frame = model.frames[frame].parent

    roles_of = {kind: get_model(kind).roles for kind in dict.fromkeys(m.kind for m in ms)}
    several_configs = len({m.config for m in ms}) > 1
    for i, m in enumerate(ms):
        for role in roles_of[m.kind]:
            name = m.refs.get(role.name)
            if name is None:
                continue
            try:
                if role.lookup == "point":
                    add_frame(model.points[model.point_index(name)].frame, i)
                elif role.lookup in ("frame", "object"):
                    add_frame(model.frame_index(name), i)
                elif role.lookup == "shape":
                    add_frame(model.shapes[model.shape_index(name)].frame, i)
                elif role.lookup == "camera":
                    add(f"camera {model.resolve('camera', name)}", i)
                elif role.lookup == "range":
                    add(f"range sensor {model.resolve('range', name)}", i)
            except Exception:  # noqa: BLE001 - a reference the problem resolved; be lenient here
                continue
        if several_configs:
            add(f"configuration {m.config}", i)
    n = len(ms)
    return {label: members for label, members in groups.items() if len(set(members)) < n}


# ---- linear algebra at the estimate ---------------------------------------------------------------------


class _Linear:
    """The problem linearised at the estimate, refitted on a subset of the measurements (priors always
    kept): refit residuals and an orthonormal basis of the Jacobian's range on those rows."""

    def __init__(self, r: np.ndarray, J: np.ndarray, rows: np.ndarray):
        self.rows = rows
        Jk, rk = J[rows], r[rows]
        if Jk.shape[1] == 0 or Jk.shape[0] == 0:
            self.U = np.zeros((len(rows), 0))
            self.rank = 0
            self.res = rk.copy()
        else:
            U, sv, _ = np.linalg.svd(Jk, full_matrices=False)
            keep = sv > _RTOL * sv[0] if sv.size and sv[0] > 0 else np.zeros(sv.shape, dtype=bool)
            self.U = U[:, keep]
            self.rank = int(keep.sum())
            self.res = rk - self.U @ (self.U.T @ rk)  # the linear refit's residual
        self.S = float(self.res @ self.res)
        self.position = np.full(r.shape[0], -1, dtype=np.int64)
        self.position[rows] = np.arange(len(rows))

    @property
    def dof(self) -> int:
        return len(self.rows) - self.rank

    def deletion(self, block_rows: np.ndarray) -> tuple[float, int]:
        """How much S drops when these rows are also set aside, and the degrees of freedom of that
        drop (rows minus the rank lost): S − S₋B = r_Bᵀ(I − H_BB)⁻¹ r_B, by Woodbury in the rank's
        dimension, with a pseudo-inverse where the block alone determines a direction."""
        pos = self.position[block_rows]
        pos = pos[pos >= 0]
        if pos.size == 0:
            return 0.0, 0
        rB = self.res[pos]
        QB = self.U[pos]
        g = QB.T @ rB
        M = np.eye(self.rank) - QB.T @ QB
        w, V = np.linalg.eigh(M) if self.rank else (np.zeros(0), np.zeros((0, 0)))
        lost = int(np.sum(w <= 1e-9))
        inv = np.where(w > 1e-9, 1.0 / np.where(w > 1e-9, w, 1.0), 0.0)
        proj = V.T @ g
        return float(rB @ rB + proj @ (inv * proj)), int(pos.size - lost)

    def deletions(self, blocks: RowBlocks | Sequence[np.ndarray], floor: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`deletion` of many small blocks (one measurement each), batched by block size in
        the block's own dimension: r_Bᵀ(I − Q_B Q_Bᵀ)⁻¹ r_B; the degrees of freedom are the
        eigenvalues of I − Q_B Q_Bᵀ above ``floor``."""
        t = np.zeros(len(blocks))
        d = np.zeros(len(blocks), dtype=np.int64)
        for size, idx, rows in blocks_by_size(blocks):
            pos = self.position[rows]  # (N, size)
            rB = self.res[pos]  # (N, size)
            QB = self.U[pos]  # (N, size, rank)
            A = np.eye(size) - QB @ np.swapaxes(QB, 1, 2)
            w, V = np.linalg.eigh(A)
            good = w > floor
            inv = np.where(good, 1.0 / np.where(good, w, 1.0), 0.0)
            proj = np.einsum("nij,ni->nj", V, rB)
            t[idx] = np.sum(inv * proj**2, axis=1)
            d[idx] = np.sum(good, axis=1)
        return t, d


_DENSE_VIEW = 1000  # views of more points are paired a slice of rows at a time


def _neighbour_sums(uv: np.ndarray, res: np.ndarray) -> np.ndarray:
    """For views of n image points each (``uv``, ``res``: (views, n, 2)): each view's pairs of
    :data:`SYSTEMATIC_NEIGHBOURS` nearest points, each pair once, summed per view — (views, 4):
    Σ rᵢ·rⱼ, Σ (rᵢ·rⱼ)², Σ ½(|rᵢ|² + |rⱼ|²) and the number of pairs."""
    n = uv.shape[1]
    d = np.zeros((uv.shape[0], n, n))
    for axis in range(uv.shape[2]):  # image points (u, v) or 3-D points (x, y, z)
        d += (uv[:, :, None, axis] - uv[:, None, :, axis]) ** 2
    d[:, np.arange(n), np.arange(n)] = np.inf
    kth = np.partition(d, SYSTEMATIC_NEIGHBOURS - 1, axis=2)[:, :, SYSTEMATIC_NEIGHBOURS - 1 : SYSTEMATIC_NEIGHBOURS]
    near = d <= kth  # each point's nearest (ties at the k-th distance all count)
    # a pair once, whichever of its points found it; the sums over the pairs only (issue 16)
    v, i, j = np.nonzero(np.triu(near | np.swapaxes(near, 1, 2), 1))
    prod = np.einsum("pk,pk->p", res[v, i], res[v, j])
    square = np.einsum("vik,vik->vi", res, res)
    mean = 0.5 * (square[v, i] + square[v, j])
    return np.stack([np.bincount(v, w, minlength=len(uv)) for w in (prod, prod * prod, mean, None)], axis=1)


def _neighbour_sums_large(uv: np.ndarray, res: np.ndarray) -> np.ndarray:
    """:func:`_neighbour_sums` of one view of many points (``uv``, ``res``: (n, 2)), its distances a
    slice of rows at a time (an n × n matrix of a view of 10,000 points would be 800 MB)."""
    n, k = len(uv), SYSTEMATIC_NEIGHBOURS
    near = np.empty((n, k), dtype=np.int64)
    for start in range(0, n, 256):
        d = np.sum((uv[start : start + 256, None, :] - uv[None, :, :]) ** 2, axis=2)
        d[np.arange(len(d)), start + np.arange(len(d))] = np.inf
        near[start : start + 256] = np.argpartition(d, k - 1, axis=1)[:, :k]
    first = np.repeat(np.arange(n), k)
    pair = np.unique(np.minimum(first, near.ravel()) * n + np.maximum(first, near.ravel()))  # each once
    a, b = pair // n, pair % n
    prod = np.einsum("ij,ij->i", res[a], res[b])
    square = np.einsum("ij,ij->i", res, res)
    return np.array([[prod.sum(), prod @ prod, 0.5 * (square[a].sum() + square[b].sum()), len(prod)]])


def systematic_residuals(
    problem: Problem, r: np.ndarray, threshold: float = DEFAULT_THRESHOLD, exclude: Sequence[int] = ()
) -> list[Suspect]:
    """Cameras whose image points are off alike where they lie close together in the image (and
    3-D points, by the frame they are given in, off alike where they lie close together in space).

    The χ² test judges the size of the residuals against the stated σ; stated larger than the
    real noise (a detector's default), it passes a model that misses something — a lens's
    distortion left out, a target's geometry wrong — whose residuals, though within σ, are a
    smooth field across the image.  Independent noise leaves neighbouring points' residuals
    uncorrelated; such a field makes them alike.  For the image points (kinds with two values in
    pixels) of each camera and configuration — and the 3-D points (kinds with three lengths, as
    ``point3d``) of each frame and configuration, paired by measured position in space — each point is paired with its
    :data:`SYSTEMATIC_NEIGHBOURS` nearest (by measured position); over a camera's pairs,
    T = Σ rᵢ·rⱼ / √Σ (rᵢ·rⱼ)² (the whitened residual vectors) is standard normal for independent
    residuals (the pair products are uncorrelated, whatever σ), and a least-squares fit's own
    leverage only lowers it.  A camera is named when T is significant (one-sided,
    Bonferroni-corrected for the cameras), the neighbours' correlation Σ rᵢ·rⱼ / Σ ½(|rᵢ|² + |rⱼ|²)
    is at least :data:`SYSTEMATIC_MIN_CORRELATION` and the shared part at least
    :data:`SYSTEMATIC_MIN_SIZE` σ.  ``exclude``: measurements (their indices) left out — the
    outliers the fit verdict found, which a patch of neighbouring mis-detections would otherwise
    make look like a field; a view of 4 points or fewer is not tested.  Measured on the corners
    ``mbcal detect`` finds in the 5 photos of Zhang's set: T = −2.0 with OpenCV's distortion model,
    26 without it (docs/report.md).
    """
    ms = problem.measurements.measurements
    columns = problem.measurements.columns().kinds
    totals: dict[str, np.ndarray] = {}  # camera → Σ products, Σ squared products, Σ mean squares, pairs
    members: dict[str, list[np.ndarray]] = {}
    for g in problem.groups:
        # positions with neighbours: image points (two values in pixels, by camera) and 3-D points
        # (three lengths, by the frame they are given in)
        if (g.model.value_dimension, g.model.size) == ("pixel", 2):
            role, label = "camera", "camera {}"
        elif (g.model.value_dimension, g.model.size) == ("length", 3):
            role, label = "frame", "3-D points in frame {}"
        else:
            continue
        col = columns[g.model.kind]
        res_all = np.asarray(r[g.start : g.start + g.rows], dtype=float).reshape(-1, g.model.size)
        cameras, camera_code = col.refs.get(role, ([g.model.kind], np.zeros(len(col.members), dtype=np.int64)))
        cameras = [label.format(name) for name in cameras]
        view = camera_code * (int(col.config.max(initial=0)) + 1) + col.config  # a camera in a configuration
        usable = col.has_value & np.all(np.isfinite(col.values), axis=1) & np.all(np.isfinite(res_all), axis=1)
        if len(exclude):
            usable &= ~np.isin(col.members, np.asarray(exclude, dtype=np.int64))
        order = np.nonzero(usable)[0]
        order = order[np.argsort(view[order], kind="stable")]
        cut = np.flatnonzero(np.diff(view[order])) + 1
        sizes = np.diff(np.concatenate([[0], cut, [len(order)]]))
        for n in np.unique(sizes[sizes > SYSTEMATIC_NEIGHBOURS]).tolist():
            # the views with n points, a batch at a time: (views, n, n) distances of at most ~4 M values
            starts = np.concatenate([[0], cut])[sizes == n]
            per = max(1, 4_000_000 // (n * n))  # 1 beyond _DENSE_VIEW points
            for b0 in range(0, len(starts), per):
                at = order[starts[b0 : b0 + per, None] + np.arange(n)]  # (views, n) rows of col
                if n > _DENSE_VIEW:
                    sums = _neighbour_sums_large(col.values[at[0]], res_all[at[0]])
                else:
                    sums = _neighbour_sums(col.values[at], res_all[at])
                for rows, view_sums in zip(at, sums):
                    name = cameras[camera_code[rows[0]]]
                    totals[name] = totals.get(name, np.zeros(4)) + view_sums
                    members.setdefault(name, []).append(col.members[rows])
    found = []
    for camera, (total, squares, scale, count) in ((c, map(float, t)) for c, t in totals.items()):
        if not (total > 0 and squares > 0 and scale > 0):
            continue
        z = total / math.sqrt(squares)
        p = float(_bonferroni(0.5 * math.erfc(z / math.sqrt(2.0)), len(totals)))
        correlation = total / scale
        shared = math.sqrt(total / (2.0 * count))  # per value, in σ
        if p >= threshold or correlation < SYSTEMATIC_MIN_CORRELATION or shared < SYSTEMATIC_MIN_SIZE:
            continue
        ids = np.sort(np.concatenate(members[camera])).tolist()
        if camera.startswith("camera "):
            what = (
                "image points",
                "image",
                "lens distortion not estimated, a wrong target geometry, a wrong camera model",
            )
        else:
            what = "points", "space", "a dimension or a pose held at a wrong value, a wrong shape"
        found.append(
            Suspect(
                "systematic",
                camera,
                tuple(ms[i].id for i in ids),
                shared**2 * 2 * len(ids),
                p,
                correlation,
                f"{camera}: neighbouring {what[0]} are off alike (their residuals correlate "
                f"{correlation:.2f}, T = {z:.3g}, p = {p:.3g}; a smooth error of about {shared:.2g} σ across the "
                f"{what[1]}) — the model misses something the residuals show as a field ({what[2]}); the χ² test "
                "cannot see it when σ is stated larger than the residuals",
            )
        )
    return found


def distinct_minima(
    solved: Any,
    obs: Observability,
    units: Mapping[str, str],
    *,
    local: Any = None,
    scale: float = 1.0,
    ranges: tuple[np.ndarray, np.ndarray] | None = None,
    angles: Sequence[bool] | None = None,
) -> list[Suspect]:
    """Other solutions as good as the estimate: restarts of ``solved`` (a
    :class:`mbcal.solver.LeastSquaresResult`) that converged with S at most
    :data:`AMBIGUOUS_MARGIN` above the best (ΔS divided by ``scale``, the factor the covariance was
    scaled by), at a point more than :data:`AMBIGUOUS_SIGMAS` σ (``obs.std``) from the estimate in
    some unknown.  Each restart is first written nearest the estimate (``local.represent_after``:
    one rotation's two angle triples are one solution), and angles are compared modulo 2π.
    ``ranges``: the search ranges (lower, upper; nan where none): a restart outside an unknown's
    range where the estimate is inside it is the other side of what the model says the value
    could be (a lever turned half a turn with a negative length), not a second answer.
    ``angles``: which unknowns are angles (default: those shown in deg or rad).  One
    :class:`Suspect` (kind ``ambiguous``) naming the nearest-S such restart and its farthest
    unknown, or none."""
    best = int(solved.best)
    cost = np.asarray(solved.cost, dtype=float)
    if best < 0 or len(cost) < 2:
        return []
    converged = np.isin(np.asarray(solved.status), [st.value for st in Status if st.converged])
    gap = (cost - cost[best]) / (scale if scale > 0 and np.isfinite(scale) else 1.0)
    near = np.nonzero(converged & np.isfinite(cost) & (gap <= AMBIGUOUS_MARGIN))[0]
    near = near[near != best]
    if not near.size:
        return []
    x = np.asarray(solved.x, dtype=float)
    here = x[best]
    others = x[near]
    if local is not None and hasattr(local, "represent_after"):
        others = represented_after(local, others, np.broadcast_to(here, others.shape).copy())
    names = list(obs.names)
    delta = others - here
    if angles is None:  # from the display units; a caller who knows the dimensions says (radians written plain)
        angle = np.array([units.get(name) in _ANGLE_UNITS for name in names], dtype=bool)
    else:
        angle = np.asarray(angles, dtype=bool)
    delta[:, angle] = (delta[:, angle] + math.pi) % (2 * math.pi) - math.pi
    if ranges is not None:
        lower, upper = (np.asarray(v, dtype=float) for v in ranges)
        placed = here + delta  # angles written nearest the estimate

        def inside(v: np.ndarray) -> np.ndarray:
            with np.errstate(invalid="ignore"):
                return ~((v < lower) | (v > upper))  # no range (nan): inside

        keep = ~np.any(inside(here)[None, :] & ~inside(placed), axis=1)
        near, delta, others = near[keep], delta[keep], others[keep]
        if not near.size:
            return []
    std = np.asarray(obs.std, dtype=float)
    usable = np.isfinite(std) & (std > 0)  # not unobservable, not held at a limit (σ 0)
    with np.errstate(invalid="ignore"):
        z = np.where(usable, np.abs(delta) / np.where(usable, std, 1.0), 0.0)
    z = np.where(np.isfinite(z), z, 0.0)
    far = np.nonzero(z.max(axis=1) > AMBIGUOUS_SIGMAS)[0]
    if not far.size:
        return []
    k = int(far[np.argmin(gap[near[far]])])  # the one that fits best
    j = int(np.argmax(z[k]))
    restart, name, unit = int(near[k]), names[j], units.get(names[j], "")

    def shown(v: float, digits: int = 7) -> str:
        return f"{fmt(to_display(unit, v), digits)} {unit}".rstrip()

    more = f"; {far.size - 1} more restart(s) ended away from it as well" if far.size > 1 else ""
    description = (
        f"restart #{restart} converged with S = {fmt(cost[restart], 6)} (the estimate's {fmt(cost[best], 6)}) at "
        f"{name} = {shown(others[k, j])}, {fmt(z[k, j], 3)} σ from the estimate {shown(here[j])} ± "
        f"{shown(std[j], 3)}{more} — the measurements do not tell the two apart: measure what separates them, "
        "or narrow the unknown's range to the right one"
    )
    return [
        Suspect(
            "ambiguous",
            name,
            tuple(str(int(near[i])) for i in far),
            float(gap[near[k]]),
            None,
            float(z[k, j]),
            description,
        )
    ]


def _significantly_held(obs: Observability, r: np.ndarray, J: Any, linearize: Any) -> tuple[tuple[str, ...], list[str]]:
    """The unknowns held at a hard limit that the data push beyond it by more than :data:`HELD_Z`
    of their σ — the fit linearised at the estimate and refitted without the limits (a least-squares
    step from it over every unknown) — and a note for each of the others: at its limit within the
    noise.  Without the dense J (a problem analysed by blocks) every held unknown counts."""
    sides: dict[str, str] = dict(getattr(obs, "active_bounds", {}) or {})
    if not sides:
        return (), []
    if J is None or linearize is not None:
        return tuple(sides), []
    Jf = np.array(J() if callable(J) else J, dtype=float)
    pinv = np.linalg.pinv(Jf, rcond=_RTOL)
    step = -(pinv @ np.asarray(r, dtype=float))
    sigma = np.sqrt(np.maximum(np.einsum("ij,ij->i", pinv, pinv), 0.0))
    held, notes = [], []
    for name, side in sides.items():
        j = list(obs.names).index(name)
        beyond = -step[j] if side == "lower" else step[j]
        z = beyond / sigma[j] if sigma[j] > 0 else 0.0
        if z > HELD_Z:
            held.append(name)
        else:
            notes.append(
                f"{name} is at its {side} limit within the noise (the fit without the limit would put it "
                f"{max(z, 0.0):.2g} σ beyond): its σ 0 is the limit's"
            )
    return tuple(held), notes


def _bonferroni(p: float | np.ndarray, count: int) -> Any:
    return np.minimum(np.asarray(p) * max(count, 1), 1.0)


def _robust_scale(t: np.ndarray, d: np.ndarray, floor: bool = True) -> float:
    """The noise level² from the median of the deletion statistics (1 under a correct σ)."""
    ok = d > 0
    if not np.any(ok):
        return 1.0
    ratio = t[ok] / stats.chi2.median(d[ok])
    s2 = float(np.median(ratio))
    return max(s2, 1.0) if floor else max(s2, 1e-300)


# ---- the verdict -------------------------------------------------------------------------------------------


def _weak_directions(obs: Observability, fraction: float, coefficient_tol: float) -> tuple[list[WeakDirection], float]:
    """Directions of the unknowns whose σ (priors included) exceeds ``fraction`` of their ranges
    — twice their scales (the observability analysis's ``scales``: half the search range, else
    the prior σ, else max(1, |nominal|)) — and the condition number of the observable part of the
    covariance in the same scaled units.  Every unknown with a finite σ is tested, with a search
    range or without: one yardstick, the observability analysis's."""
    by_blocks = getattr(obs.covariance, "weak_directions", None)
    if by_blocks is not None:  # a structured problem's covariance (mbcal.structured.BlockCovariance): no n × n matrix
        found, condition = by_blocks(fraction, coefficient_tol)
        return [WeakDirection(names, sigma) for names, sigma in found], condition
    cov = np.asarray(obs.covariance, dtype=float)
    use = np.isfinite(np.diag(cov))  # the unobservable unknowns' rows and columns are inf
    out: list[WeakDirection] = []
    if not np.any(use):
        return out, 1.0
    if obs.scaled_eigen is not None and np.all(use):  # the analysis's own SVD: the same, more precisely
        lam, V = obs.scaled_eigen
    else:
        scales = np.asarray(obs.scales, dtype=float)[use]
        Cs = cov[np.ix_(use, use)] / np.outer(scales, scales)  # in scales: σ 1 is half the range
        lam, V = np.linalg.eigh((Cs + Cs.T) / 2)
    positive = lam[lam > 0]
    condition = float(np.sqrt(positive.max() / positive.min())) if positive.size else 1.0
    names = [nm for nm, u in zip(obs.names, use) if u]
    for k in np.argsort(-lam):
        sigma = float(np.sqrt(max(lam[k], 0.0))) / 2.0  # a fraction of the range: twice the scale
        if not sigma > fraction:
            break
        v = V[:, k]
        big = np.max(np.abs(v))
        order = [j for j in np.argsort(-np.abs(v)) if abs(v[j]) >= coefficient_tol * big]
        out.append(WeakDirection(tuple(names[j] for j in order), sigma))
    return out, condition


def _weak_part(
    problem: Problem, obs: Observability, config: FitConfig, observability: ObservabilityConfig | None
) -> dict[str, Any]:
    """The verdict's determination fields: weak directions, condition number, observability."""
    tol = (observability or ObservabilityConfig()).coefficient_tol
    weak, condition = _weak_directions(obs, config.weak_fraction, tol)
    params = problem.params
    weak = [WeakDirection(w.names, w.sigma, tuple(scale_stand_ins(w.names, params))) for w in weak]
    determined = bool(obs.observable_with_priors)
    if not determined and not np.any(np.isfinite(np.asarray(obs.std, dtype=float)) & ~obs.fixed):
        condition = math.inf  # no free unknown is determined: no finite part to take it over (not 1.0)
    return {
        "weak": tuple(weak),
        "weak_fraction": config.weak_fraction,
        "condition": condition,
        "determined": determined,
        "rank": int(obs.rank_with_priors),
        "unknowns": int(obs.n_free),
    }


def assess_plan(
    problem: Problem,
    obs: Observability,
    *,
    config: FitConfig | None = None,
    observability: ObservabilityConfig | None = None,
    accept: bool = False,
) -> FitVerdict:
    """The verdict on a plan (no measured values): only whether every unknown is determined and
    well determined."""
    config = config or FitConfig()
    return FitVerdict(
        chi2=None,
        dof=0,
        p_value=None,
        threshold=config.threshold,
        consistent=True,
        max_condition=config.max_condition,
        accepted=accept,
        **_weak_part(problem, obs, config, observability),
    )


def assess_fit(
    problem: Problem,
    r: np.ndarray,
    J: np.ndarray | Callable[[], np.ndarray] | None,
    obs: Observability,
    *,
    loss: str = "linear",
    config: FitConfig | None = None,
    observability: ObservabilityConfig | None = None,
    accept: bool = False,
    groups: Mapping[str, Sequence[int]] | None = None,
    linearize: Callable[[np.ndarray], Any] | None = None,
    ambiguous: Sequence[Suspect] = (),
    leverage: bool | Sequence[int] = False,
) -> FitVerdict:
    """The verdict on a calibration at its estimate.

    Parameters
    ----------
    problem : Problem
    r, J : arrays
        The whitened residual (measurement rows, then prior rows) and its Jacobian at the estimate
        (or a function returning it: called only when the fit is not consistent).
    obs : Observability
        The analysis at the estimate (its rank, scales and covariance).
    loss : str
        The solver's loss: with a robust one, the outliers it down-weights are set aside first.
    groups : mapping, optional
        Label → measurement indices (default: :func:`measurement_groups`).
    linearize : callable, optional
        rows → the problem linearised on those rows, refitted (``S``, ``dof``, ``deletion``,
        ``deletions`` as :class:`_Linear`); ``J`` may then be None.  A structured problem's
        (:class:`mbcal.structured.StructuredLinear`) works from its blocks, without the m × n J.
    ambiguous : sequence of Suspect
        The other solutions the restarts found as good (:func:`distinct_minima`).
    leverage : bool or sequence of int
        Name the measurements that alone determine part of the unknowns (``untested``): True for
        every measurement (an SVD of ``J``, or ``linearize`` of every row: the caller says whether
        that is cheap), or the indices of the measurements to test.
    """
    config = config or FitConfig()
    alpha = config.threshold
    r = np.asarray(r, dtype=float)
    S = float(r @ r)
    m_rows = problem.n_residuals
    dof = max(m_rows - int(obs.rank_with_priors), 0)
    weak = _weak_part(problem, obs, config, observability)
    systematic = tuple(systematic_residuals(problem, r, alpha))
    ms = problem.measurements.measurements
    ids = [m.id for m in ms]
    blocks = problem.row_blocks
    Jd: np.ndarray | None = None

    def dense_j() -> np.ndarray:
        nonlocal Jd
        if Jd is None:
            Jd = np.array(J() if callable(J) else J, dtype=float)
            held = [obs.names.index(name) for name in getattr(obs, "active_bounds", {}) if name in obs.names]
            Jd[:, held] = 0.0  # unknowns held at an active hard bound are not refitted
        return Jd

    held_names, held_notes = _significantly_held(obs, r, J, linearize)
    untested: tuple[str, ...] = ()
    whole: Any = None  # the linearisation on every row: the outlier search's first round reuses it
    probed = list(range(len(ms))) if leverage is True else [int(i) for i in (leverage or ())]
    if probed and (J is not None or linearize is not None):
        # d < the block's size: deleting the measurement loses rank, its residual is forced to ~0
        every = np.arange(r.shape[0])
        whole = linearize(every) if linearize is not None else _Linear(r, dense_j(), every)
        _, d = whole.deletions(blocks.take(probed), floor=1.0 - UNTESTED_LEVERAGE)
        sizes = blocks.sizes[probed]
        untested = tuple(ids[probed[k]] for k in np.nonzero((sizes > 0) & (d < sizes))[0].tolist())
    common = dict(
        threshold=alpha,
        loss=str(loss),
        max_condition=config.max_condition,
        accepted=accept,
        systematic=systematic,
        ambiguous=tuple(ambiguous),
        untested=untested,
        held=held_names,
        notes=tuple(held_notes),
        **weak,
    )
    if dof == 0:
        return FitVerdict(S, 0, None, consistent=True, **common)  # type: ignore[arg-type]
    p = float(stats.chi2.sf(S, dof))
    common["sigma_too_large"] = bool(S / dof < TOO_SMALL_REDUCED_CHI2 and 1.0 - chi2_sf(S, dof) < alpha)
    common["chi2_scaled"] = obs.chi2_scale != 1.0
    robust = str(loss) != "linear"
    if p >= alpha and not robust:  # consistent: nothing to look for (and nothing below computed, issue 16)
        return FitVerdict(S, dof, p, consistent=True, **common)  # type: ignore[arg-type]
    if linearize is None:
        dense_j()
    prior_rows = np.arange(problem.size, problem.n_residuals)

    def rows_of(members) -> np.ndarray:
        parts = [blocks[i] for i in members]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)

    def linear(kept: np.ndarray) -> Any:
        if whole is not None and kept.all():
            return whole
        rows = np.concatenate([rows_of(np.nonzero(kept)[0]), prior_rows])
        if linearize is not None:
            return linearize(rows)
        assert Jd is not None
        return _Linear(r, Jd, rows)

    n_meas = len(ms)
    normalized = np.array([float(np.sqrt(np.sum(r[b] ** 2))) for b in blocks])

    # 1. Outliers: the worst significant one at a time (a tenth of them at a time when there are many),
    #    each round refitted without those found so far.
    kept = np.ones(n_meas, dtype=bool)
    outliers: list[int] = []
    s2 = 1.0
    max_outliers = max(1, n_meas // 2)
    for _ in range(_MAX_ROUNDS):
        if len(outliers) >= max_outliers:
            break
        lin = linear(kept)
        idx = np.nonzero(kept)[0]
        t, d = lin.deletions(blocks.take(idx))
        s2 = _robust_scale(t, d)
        with np.errstate(invalid="ignore"):
            logp = np.where(d > 0, stats.chi2.logsf(t / s2, np.maximum(d, 1)), 0.0)
        # Bonferroni in logs: p · count < alpha, without underflow for the grossest outliers.
        significant = np.nonzero(logp + np.log(max(int(np.sum(d > 0)), 1)) < np.log(alpha))[0]
        if significant.size == 0:
            break
        take = significant[np.argsort(logp[significant])][: max(1, significant.size // 10)]
        take = take[: max_outliers - len(outliers)]
        outliers.extend(int(idx[j]) for j in take)
        kept[idx[take]] = False

    # 2. Structural errors: groups mostly made of outliers, then groups significant on their own.
    source = groups if groups is not None else measurement_groups(problem)
    by_group: dict[str, list[int]] = {k: sorted(set(v)) for k, v in source.items() if len(set(v)) >= config.min_group}
    outlier_set = set(outliers)
    structural: list[tuple[str, list[int], float, float | None]] = []  # label, members, excess, p
    attributed: set[int] = set()
    concentrated = []
    for label, members in by_group.items():
        hit = outlier_set.intersection(members)
        if len(hit) >= config.min_group and 2 * len(hit) >= len(members):
            concentrated.append((len(hit) / len(members), -len(members), label))
    for _, _, label in sorted(concentrated, reverse=True):
        members = by_group[label]
        hit = outlier_set.intersection(members) - attributed
        if len(hit) < config.min_group:
            continue  # its outliers are already explained by a more specific group
        rest = np.ones(n_meas, dtype=bool)
        rest[list(outlier_set - set(members))] = False
        excess, _ = linear(rest).deletion(rows_of(members))
        structural.append((label, members, excess, None))
        attributed.update(members)
    set_aside = np.ones(n_meas, dtype=bool)
    set_aside[list(outlier_set | attributed)] = False
    while True:
        lin = linear(set_aside)
        best = None
        tested = 0
        candidates = []
        for label, members in by_group.items():
            if any(label == s[0] for s in structural):
                continue
            live = [i for i in members if set_aside[i]]
            if len(live) < config.min_group:
                continue
            drop, dd = lin.deletion(rows_of(live))
            if dd <= 0 or lin.dof - dd <= 0:
                continue
            tested += 1
            candidates.append((drop / dd, drop, dd, label, live))
        for _intensity, drop, dd, label, live in sorted(candidates, key=lambda c: -c[0]):
            pg = float(_bonferroni(stats.chi2.sf(drop / s2, dd), tested))
            if pg < alpha:
                best = (label, live, drop, pg)
                break
        if best is None:
            break
        label, live, drop, pg = best
        structural.append((label, by_group[label], drop, pg))
        attributed.update(live)
        set_aside[live] = False
    outliers = [i for i in outliers if i not in attributed]

    # 3. What remains: σ too small?
    rest = np.ones(n_meas, dtype=bool)
    rest[outliers] = False
    rest[list(attributed)] = False
    lin_rest = linear(rest)
    # None: what is left has no redundancy to test (every degree of freedom went to what was set aside)
    p_rest = float(stats.chi2.sf(lin_rest.S, lin_rest.dof)) if lin_rest.dof > 0 else None

    suspects: list[Suspect] = []
    if outliers:
        without = np.ones(n_meas, dtype=bool)
        without[outliers] = False
        excess = S - linear(without).S
        shown = sorted(outliers, key=lambda i: -normalized[i])
        listed = ", ".join(f"{ids[i]} ({normalized[i]:.3g}σ)" for i in shown[:10]) + (" …" if len(shown) > 10 else "")
        suspects.append(
            Suspect(
                "outliers",
                "measurements",
                tuple(ids[i] for i in shown),
                excess,
                None,
                None,
                f"{len(shown)} outlying measurement(s): {listed} — setting them aside lowers S by {excess:.4g}",
            )
        )
    for label, members, group_excess, p_group in structural:
        big = sum(1 for i in members if normalized[i] > 3)
        suspects.append(
            Suspect(
                "structural",
                label,
                tuple(ids[i] for i in members),
                group_excess,
                p_group,
                None,
                f"{label}: its {len(members)} measurements are systematically off ({big} beyond 3σ; setting "
                f"them aside lowers S by {group_excess:.4g}) — a structural error of the model: check its "
                "dimensions, its pose and the points on it",
            )
        )
    if p_rest is not None and p_rest < alpha:
        factor = float(np.sqrt(lin_rest.S / lin_rest.dof))
        others = " the rest:" if outliers or structural else ""
        suspects.append(
            Suspect(
                "sigma",
                "σ",
                (),
                lin_rest.S - lin_rest.dof,
                p_rest,
                factor,
                f"σ set too small:{others} the residuals are uniformly about {factor:.3g} × the stated σ "
                f"(S = {lin_rest.S:.4g} for {lin_rest.dof} degrees of freedom) — if that is the real noise, state σ "
                f"about {factor:.3g} times larger; otherwise an error common to all measurements (a parameter "
                "held at a wrong value, a wrong sensor model)",
            )
        )
    suspects.sort(key=lambda s: -s.excess)
    if outlier_set:
        # A patch of neighbouring outliers would look like a field: with a robust loss (its estimate
        # not pulled by them) the rest is tested without them; a plain least-squares estimate is
        # pulled by them, its other residuals too — the field is judged on the robust fit the
        # report then recommends.
        found = systematic_residuals(problem, r, alpha, exclude=sorted(outlier_set)) if robust else []
        common["systematic"] = tuple(found)
    notes: list[str] = list(common.pop("notes"))  # type: ignore[arg-type]
    if robust:
        # The robust loss was asked to ignore outliers: the test covers what is left.
        aside = tuple(ids[i] for i in sorted(outliers, key=lambda i: -normalized[i]))
        chi2_rest = lin_rest.S if aside or structural else S
        dof_rest = lin_rest.dof if aside or structural else dof
        p_shown = p_rest if aside or structural else p
        consistent = not structural and (p_shown is None or p_shown >= alpha)  # None: nothing left to test
        suspects = [s for s in suspects if s.kind != "outliers" or not consistent]
        if aside:
            notes.append(f"the {str(loss)} loss sets aside {len(aside)} outlier(s): {', '.join(aside[:10])}")
        if not consistent and not suspects:
            notes.append("no single measurement or group explains it: the model may be wrong everywhere")
        return FitVerdict(
            chi2_rest,
            dof_rest,
            p_shown,
            consistent=consistent,
            suspects=tuple(suspects),
            set_aside=aside,
            notes=tuple(notes),
            **common,  # type: ignore[arg-type]
        )
    if not suspects:
        notes.append("no single measurement or group explains it: the model may be wrong everywhere")
    return FitVerdict(S, dof, p, consistent=False, suspects=tuple(suspects), notes=tuple(notes), **common)  # type: ignore[arg-type]
