"""What a calibration or a plan analysis found, and its report: text tables for people, JSON for
programs (docs/report.md)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from typing import Any, overload

import numpy as np

from mbcal.export.mdl import write_calibrated_model
from mbcal.fit import FitVerdict
from mbcal.measurements.registry import get_model
from mbcal.observability import MadeWhenRead, Observability, PointUncertainty, weak_scale_text
from mbcal.problem import Problem
from mbcal.solver import LeastSquaresResult, SolverConfig, Status
from mbcal.structured import BlockCovariance
from mbcal.text import fmt, table
from mbcal.units import to_display

__all__ = [
    "CalibrationResult",
    "PlanAnalysis",
    "ResidualRow",
    "ResidualRows",
    "DeferredPoints",
    "RunInfo",
    "result_json",
    "result_text",
    "plan_json",
    "plan_text",
    "REPORT_FORMAT",
]

REPORT_FORMAT = "mbcal-report-1"


@dataclass(frozen=True, slots=True)  # 2,000 views: 108,000 rows (issue 15)
class ResidualRow:
    """One measurement at the solution."""

    id: str
    kind: str
    config: str
    refs: dict[str, str]
    measured: np.ndarray
    predicted: np.ndarray
    normalized: float  # √((h − y)ᵀ W (h − y)): the residual in units of its σ

    @property
    def residual(self) -> np.ndarray:
        """measured − predicted, in the measurement's units."""
        return self.measured - self.predicted

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "config": self.config,
            "refs": self.refs,
            "measured": [float(v) for v in self.measured],
            "predicted": [float(v) for v in self.predicted],
            "residual": [float(v) for v in self.residual],
            "normalized": float(self.normalized),
        }


class ResidualRows(MadeWhenRead[ResidualRow]):
    """Every measurement at the solution, in the set's order: a list of :class:`ResidualRow` to
    its readers, kept as one array per kind, each row made when it is read (issue 16: the 702 rows
    of a 13-view calibration were ~1 ms of it as objects; issue 15: 108,000 of them at 2,000 views).

    ``normalized`` is every row's normalised residual (an array); :meth:`kind` gives one kind's
    measured and predicted values as arrays."""

    __slots__ = ("_measurements", "_kinds", "_parts", "_part", "_row", "normalized")

    def __init__(self, measurements: Sequence[Any], kinds: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]):
        """``kinds``: per kind, (members: indices into ``measurements``, measured (k, s),
        predicted (k, s)); ``normalized`` is filled in by the caller (one value per measurement)."""
        self._measurements = measurements
        self._kinds = kinds
        self._parts = list(kinds.values())
        self._part = np.zeros(len(measurements), dtype=np.int32)
        self._row = np.zeros(len(measurements), dtype=np.int64)
        for p, (members, _y, _h) in enumerate(kinds.values()):
            self._part[members] = p
            self._row[members] = np.arange(len(members))
        self.normalized = np.zeros(len(measurements))

    def __len__(self) -> int:
        return len(self._measurements)

    def _make(self, k: int) -> ResidualRow:
        m = self._measurements[k]
        _members, Y, H = self._parts[int(self._part[k])]
        r = int(self._row[k])
        return ResidualRow(m.id, m.kind, m.config, m.refs, Y[r], H[r], float(self.normalized[k]))

    @property
    def kinds(self) -> list[str]:
        return list(self._kinds)

    def kind(self, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(members, measured, predicted) of one kind: indices into the set, (k, size) arrays."""
        return self._kinds[kind]

    def worst(self, count: int | None = None, *, above: float = -np.inf) -> list[ResidualRow]:
        """The rows with the largest normalised residuals (above ``above``), worst first."""
        order = np.argsort(-self.normalized, kind="stable")
        order = order[self.normalized[order] > above]
        return [self._make(k) for k in order[:count].tolist()]


class DeferredPoints(Sequence[PointUncertainty]):
    """The point uncertainties of a calibration, computed when first read (issue 16: ~1 ms of a
    warm 13-view camera calibration, which OpenCV does not compute either, paid by whoever reads
    them: the report, its JSON, the studio).  The same numbers as computing them at once: the
    function holds the estimate and its covariance."""

    __slots__ = ("_compute", "_value")

    def __init__(self, compute: Callable[[], Sequence[PointUncertainty]]):
        self._compute: Callable[[], Sequence[PointUncertainty]] | None = compute
        self._value: Sequence[PointUncertainty] | None = None

    @property
    def value(self) -> Sequence[PointUncertainty]:
        if self._value is None:
            assert self._compute is not None
            self._value, self._compute = self._compute(), None
        return self._value

    def __len__(self) -> int:
        return len(self.value)

    @overload
    def __getitem__(self, i: int) -> PointUncertainty: ...

    @overload
    def __getitem__(self, i: slice) -> Sequence[PointUncertainty]: ...

    def __getitem__(self, i):
        return self.value[i]

    def __iter__(self) -> Iterator[PointUncertainty]:
        return iter(self.value)


@dataclass(frozen=True)
class RunInfo:
    """How a calibration was run: what the report's ``restarts`` and ``not_visible`` come from."""

    restarts: int = 0
    """Number of starting points."""
    seed: int | None = None
    """Seed of the random starting points."""
    config: SolverConfig | None = None
    """The solver's settings."""
    scale_covariance: bool = False
    """Whether the covariance was scaled by the reduced χ²."""
    not_visible: tuple[str, ...] = ()
    """Ids of the measurements that cannot be made at the solution."""
    note: str = ""
    """How the number of restarts was chosen, when a workflow chose it (``calibrate_cameras``)."""

    def as_dict(self) -> dict[str, Any]:
        """The fields as a dict (``not_visible`` as a list): the ``info`` of mbcal 0.1."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["not_visible"] = list(self.not_visible)
        return out


@dataclass
class CalibrationResult:
    """Everything a calibration found.

    Values, σ and covariance are in SI units (metres, radians); ``display`` converts angles to
    degrees for reports.  Unobservable unknowns have σ = inf (never NaN).
    """

    problem: Problem
    solver: LeastSquaresResult
    x: np.ndarray
    x_initial: np.ndarray
    observability: Observability
    residuals: ResidualRows  # a list of ResidualRow to its readers, made when read
    points: Sequence[PointUncertainty]  # a PointUncertainties from calibrate: made when read
    cost: float
    rms: dict[str, float]
    elapsed: float
    outlier_threshold: float = 3.0
    run: RunInfo = field(default_factory=RunInfo)
    verdict: FitVerdict | None = None
    """Whether the fit is consistent with the stated σ (and what to suspect if not), and whether every
    unknown is well determined (:mod:`mbcal.fit`)."""

    @property
    def info(self) -> dict[str, Any]:
        """``run`` as a dict — the untyped form of mbcal 0.1, kept for one release (use ``run``)."""
        return self.run.as_dict()

    # ---- headline numbers ----------------------------------------------------------------------

    @property
    def names(self) -> list[str]:
        return self.problem.unknown_names

    @property
    def values(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.x)))

    @property
    def initial(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.x_initial)))

    @property
    def std(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.observability.std)))

    @property
    def covariance(self) -> np.ndarray:
        return self.observability.covariance

    @property
    def correlation(self) -> np.ndarray:
        return self.observability.correlation

    @property
    def status(self) -> Status:
        return self.solver.status_best

    @property
    def converged(self) -> bool:
        return self.solver.best >= 0 and self.status.converged

    @property
    def observable(self) -> bool:
        return self.observability.observable_with_priors

    @property
    def ok(self) -> bool:
        """Converged, every unknown determined, and the verdict trustworthy: the fit consistent with the
        stated σ and no direction weakly determined (unless accepted, ``accept_poor_fit``)."""
        return self.converged and self.observable and (self.verdict is None or self.verdict.ok)

    @property
    def consistent(self) -> bool:
        """The χ² test passed (or could not be made)."""
        return self.verdict is None or self.verdict.consistent

    @property
    def n_measurements(self) -> int:
        return self.problem.size

    @property
    def dof(self) -> int:
        return max(self.problem.n_residuals - self.observability.rank_with_priors, 0)

    @property
    def reduced_chi2(self) -> float:
        return self.cost / self.dof if self.dof > 0 else float("nan")

    @property
    def outliers(self) -> list[ResidualRow]:
        """Measurements whose normalised residual exceeds the threshold, worst first."""
        return self.residuals.worst(above=self.outlier_threshold)

    def display(self, name: str, value: float) -> float:
        return to_display(self.problem.params.info(name).unit, value)

    def unit(self, name: str) -> str:
        return self.problem.params.info(name).unit

    # ---- output ------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """The report as plain data (schema: docs/report.md)."""
        return result_json(self)

    def summary(self, *, max_residuals: int = 15) -> str:
        """The report as text tables."""
        return result_text(self, max_residuals=max_residuals)

    def write_model(self, path, *, overwrite: bool = True) -> None:
        """Write the model with the estimated values as its nominal values (the input is untouched)."""
        note = []
        if self.problem.measurements.path:
            note.append(
                f"with {self.problem.measurements.path}: S = {self.cost:.6g}, "
                + ", ".join(f"RMS {k} {v:.4g}" for k, v in self.rms.items())
            )
        if not self.ok:
            # A model written from a fit that is not to be trusted says so where it is read.
            why = [] if self.converged else [f"the solve did not converge ({self.status.label})"]
            why += [] if self.observable else ["not every unknown is observable"]
            note.append("NOT A TRUSTWORTHY FIT" + (": " + "; ".join(why) if why else ""))
            if self.verdict is not None:
                note.append(f"verdict: {self.verdict.verdict()}")
        elif self.verdict is not None and not self.verdict.trustworthy:
            # accepted (--accept-poor-fit): the model file still says what was accepted
            note.append(f"verdict: {self.verdict.verdict()}")
        write_calibrated_model(
            self.problem.model,
            self.values,
            path,
            std=self.std,
            note=note,
            overwrite=overwrite,
            at_bound=self.observability.active_bounds,
        )


@dataclass
class PlanAnalysis:
    """Is a measurement plan enough? (``mbcal observe``)."""

    problem: Problem
    x: np.ndarray
    observability: Observability
    points: Sequence[PointUncertainty]  # a PointUncertainties from calibrate: made when read
    invisible: list[str]
    verdict: FitVerdict | None = None
    """Whether every unknown would be well determined (no weak direction, condition number in bounds)."""

    @property
    def names(self) -> list[str]:
        return self.problem.unknown_names

    @property
    def ok(self) -> bool:
        """Every unknown determined (priors included) and well determined (unless accepted)."""
        return self.observability.observable_with_priors and (self.verdict is None or self.verdict.ok)

    @property
    def std(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.observability.std)))

    def to_json(self) -> dict[str, Any]:
        return plan_json(self)

    def summary(self) -> str:
        return plan_text(self)


def _num(v: float) -> float | None:
    """JSON has no inf/NaN: they become null (and the report says why)."""
    return float(v) if v is not None and np.isfinite(v) else None


def _parameters_json(names, units, x, x0, std) -> dict[str, Any]:
    out = {}
    for i, name in enumerate(names):
        unit = units[name]
        entry: dict[str, Any] = {
            "value": float(x[i]),
            "std": _num(std[i]),
            "initial": float(x0[i]) if x0 is not None else None,
            "unit": _si_unit(unit),
            "observable": bool(np.isfinite(std[i])),
        }
        if unit == "deg":
            entry["display"] = {"unit": "deg", "value": to_display(unit, x[i]), "std": _num(to_display(unit, std[i]))}
        out[name] = entry
    return out


def _observability_json(obs) -> dict[str, Any]:
    return {
        "observable": obs.observable,
        "observable_with_priors": obs.observable_with_priors,
        "rank": obs.rank,
        "unknowns": obs.n,
        "condition_number": _num(obs.condition),
        "singular_values": [float(s) for s in obs.singular_values],
        "unobservable": [c.to_json() for c in obs.unobservable],
        "weak": [{**c.to_json(), "sigma_scaled": _num(c.sigma)} for c in obs.weak],
        "suggestions": [s.to_json() for s in obs.suggestions],
        "verdict": obs.verdict(),
    }


def _covariance_json(names, cov, corr) -> dict[str, Any]:
    if isinstance(cov, BlockCovariance):
        return _block_covariance_json(cov)
    return {
        "names": list(names),
        "covariance": _matrix_json(cov),
        "correlation": _matrix_json(corr),
    }


def _matrix_json(a) -> list[list[float | None]]:
    return [[_num(v) for v in row] for row in np.asarray(a, dtype=float)]


def _block_covariance_json(cov: BlockCovariance) -> dict[str, Any]:
    """A structured problem's covariance by its blocks, never n × n (issue 15: 2,000 views of a
    board have 12,009 unknowns, a 144-million-entry matrix): the shared unknowns' covariance and
    correlation, and each block's own (its marginal; σ of every unknown is in ``parameters``)."""
    s = cov.structure
    corr = cov.correlation()

    def parts(idx: np.ndarray) -> list[dict[str, Any]]:
        a, b = idx[:, :, None], idx[:, None, :]  # every block's (k, k) at once
        C, R = cov[a, b], corr[a, b]
        return [
            {"names": [cov.names[j] for j in row], "covariance": _matrix_json(C[k]), "correlation": _matrix_json(R[k])}
            for k, row in enumerate(idx)
        ]

    return {"names": list(cov.names), "form": "blocks", "shared": parts(s.shared), "blocks": parts(s.blocks)}


# ---- hard bounds active at the solution (issue 14, item 2) ---------------------------------------


def _active_bounds_json(r: CalibrationResult) -> list[dict[str, Any]]:
    """The unknowns held at an active hard bound: which bound, its value (SI) and unit."""
    out = []
    for name, side in r.observability.active_bounds.items():
        info = r.problem.params.info(name)
        limit = info.limit_lower if side == "lower" else info.limit_upper
        unit = info.unit
        value = None if limit is None else _num(limit)
        out.append({"name": name, "bound": side, "limit": value, "unit": _si_unit(unit)})
    return out


def _active_bounds_text(r: CalibrationResult) -> list[str]:
    bounds = r.observability.active_bounds
    if not bounds:
        return []
    parts = []
    for entry in _active_bounds_json(r):
        unit = r.unit(entry["name"])
        parts.append(f"{entry['name']} at its {entry['bound']} limit {_value_cell(unit, entry['limit'])}")
    return [
        f"at an active bound ({len(bounds)}): " + "; ".join(parts),
        "  the data push these past their limits: each is held at its bound, with σ 0, and the covariance "
        "of the others is computed with it held",
    ]


def _si_unit(unit: str) -> str:
    return "rad" if unit == "deg" else unit


def _far_outside_ranges(r: CalibrationResult) -> list[dict[str, Any]]:
    """Each estimate that lies outside its search range by more than half the range's width
    (name, value, lower, upper in SI units, unit).  The search ranges bound the random starts, not
    the estimates, so this is no error — but an estimate that far out (cx = 608 px for a range of
    [220, 420], from corners in pixels of another resolution) says that the data or the model are
    not what the ranges expected."""
    out = []
    for i, name in enumerate(r.names):
        info = r.problem.params.info(name)
        lower, upper = getattr(info, "lower", None), getattr(info, "upper", None)
        x = float(r.x[i])
        if lower is None or upper is None or not upper > lower or not np.isfinite(x):
            continue
        if x < lower - (upper - lower) / 2 or x > upper + (upper - lower) / 2:
            unit = r.unit(name)
            out.append({"name": name, "value": x, "lower": float(lower), "upper": float(upper), "unit": _si_unit(unit)})
    return out


def _far_outside_ranges_text(r: CalibrationResult) -> list[str]:
    """The note of :func:`_far_outside_ranges` in the text report."""
    parts = []
    for entry in _far_outside_ranges(r):
        unit = r.unit(entry["name"])
        parts.append(
            f"{entry['name']} = {_value_cell(unit, entry['value'])} (search range "
            f"[{_value_cell(unit, entry['lower'])}, {_value_cell(unit, entry['upper'])}])"
        )
    if not parts:
        return []
    return [
        f"note: far outside the search range ({len(parts)}): "
        + "; ".join(parts[:8])
        + (" …" if len(parts) > 8 else ""),
        "  the ranges only bound the random starts; an estimate this far out often means measurements in other "
        "units or pixels, or a model that does not fit them",
    ]


def result_json(r: CalibrationResult) -> dict[str, Any]:
    """The calibration report as JSON-ready data."""
    units = {n: r.unit(n) for n in r.names}
    solver = r.solver
    status = "converged" if r.converged else ("failed" if solver.best < 0 else "not_converged")
    statuses = solver.statuses()
    return {
        "format": REPORT_FORMAT,
        "status": status,
        "message": r.status.message,
        "ok": r.ok,
        "model": r.problem.model.path,
        "measurements": r.problem.measurements.path,
        "cost": float(r.cost),
        "rms": {k: float(v) for k, v in r.rms.items()},
        "rms_normalized": float(np.sqrt(r.cost / max(r.problem.n_residuals, 1))),
        "reduced_chi2": _num(r.reduced_chi2),
        "dof": r.dof,
        "n_measurements": len(r.problem.measurements),
        "n_residuals": r.problem.n_residuals,
        "parameters": _parameters_json(r.names, units, r.x, r.x_initial, r.observability.std),
        "observable": r.observable,
        "rank": r.observability.rank,
        "unobservable": [c.to_json() for c in r.observability.unobservable],
        "observability": _observability_json(r.observability),
        "covariance": _covariance_json(r.names, r.covariance, r.correlation),
        "restarts": {
            "count": int(len(solver.cost)),
            "converged": int(np.sum(solver.converged)),
            "best": int(solver.best),
            "seed": r.run.seed,
            "chosen": r.run.note,
            "runs": [
                {
                    "index": i,
                    "status": statuses[i].label,
                    "cost": _num(solver.cost[i]),
                    "iterations": int(solver.iterations[i]),
                    "initial": [float(v) for v in solver.x0[i]],
                    "final": [float(v) for v in solver.x[i]],
                }
                for i in range(len(solver.cost))
            ],
        },
        "residuals": [row.to_json() for row in r.residuals],
        "outliers": {"threshold": r.outlier_threshold, "ids": [row.id for row in r.outliers]},
        "not_visible": list(r.run.not_visible),
        "active_bounds": _active_bounds_json(r),
        "outside_search_range": _far_outside_ranges(r),
        **({"fit": r.verdict.to_json()} if r.verdict is not None else {}),
        "points": [p.to_json() for p in r.points],
        "solver": {
            "loss": str(solver.config.loss),
            "loss_scale": solver.config.loss_scale,
            "max_iterations": solver.config.max_iterations,
            "ftol": solver.config.ftol,
            "xtol": solver.config.xtol,
            "gtol": solver.config.gtol,
        },
        "elapsed_s": float(r.elapsed),
    }


def _value_cell(unit: str, v: float) -> str:
    if not np.isfinite(v):
        return "unobservable"
    return f"{fmt(to_display(unit, v), 7)} {unit}".rstrip()


def _std_cell(unit: str, v: float) -> str:
    if not np.isfinite(v):
        return "∞ (unobservable)"
    return f"{fmt(to_display(unit, v), 3)} {unit}".rstrip()


def _observability_text(obs, params=None) -> list[str]:
    out = ["", f"observability: {obs.verdict()}"]
    for c in obs.unobservable:
        out.append(f"  - {c.describe()}")
    for c in obs.weak:
        names = ", ".join(c.names)
        scale = weak_scale_text(c.names, params)  # what c.sigma is in: each unknown's scale, as the analysis scales it
        out.append(f"  - weakly observable ({names}): σ along this direction is {c.sigma:.2g} × {scale}")
    if obs.suggestions:
        out.append("  measurements that would help most:")
        for s in obs.suggestions:
            out.append(f"    · {s.text}")
    elif not obs.observable:
        out.append(
            "  no single additional measurement in these configurations helps: measure in another configuration "
            "(attitude, view), or fix the parameters named above to known values"
        )
    return out


def _points_text(points, model) -> list[str]:
    if not points:
        return []

    def mm(sigma: float) -> str:
        return "∞" if not np.isfinite(sigma) else f"{1000 * sigma:.3g}"

    shown = points[:40]
    extra = [f"… {len(points) - 40} more points in the JSON report"] if len(points) > 40 else []
    if not model.cameras:  # no line of sight to split along (with cameras, every point has one)
        rows = [[model.short_name("point", p.point), p.configuration, mm(p.perpendicular), mm(p.total)] for p in shown]
        text = table(
            ["point", "config", "σ max (mm)", "σ total (mm)"],
            rows,
            align="llrr",
            title="\nposition uncertainty of the points (no camera: the largest σ in any direction, and √trace):",
        )
        return [text, *extra]
    rows = [
        [
            model.short_name("point", p.point),
            p.configuration,
            model.short_name("camera", p.camera) if p.camera else "—",
            mm(p.perpendicular),
            mm(p.parallel),
        ]
        for p in shown
    ]
    text = table(
        ["point", "config", "line of sight", "σ⟂ (mm)", "σ∥ (mm)"],
        rows,
        align="lllrr",
        title="\nposition uncertainty of the points (⟂ and ∥ to the camera's line of sight):",
    )
    return [text, *extra]


# The unit an RMS residual is shown in, by the measurement kind's value dimension (SI values).
_RMS_UNITS = {"pixel": "px", "length": "m", "angle": "rad"}


def _roles(kind: str):
    return get_model(kind).roles


def _short(model, lookup: str, name: str) -> str:
    table = "frame" if lookup == "object" else lookup
    try:
        return model.short_name(table, name)
    except KeyError:
        return name


def result_text(r: CalibrationResult, *, max_residuals: int = 15) -> str:
    """The calibration report as text."""
    out = []
    solver = r.solver
    head = "converged" if r.converged else "NOT converged"
    message = r.status.message
    # "converged: converged: ..." said it twice: the status's message starts with its verdict
    out.append(message if r.converged and message.startswith("converged:") else f"{head}: {message}")
    rms = ", ".join(
        f"{k} {v:.4g} {_RMS_UNITS.get(get_model(k).value_dimension, '')}".rstrip() for k, v in r.rms.items()
    )
    loss = str(r.solver.config.loss)
    if loss == "linear":
        cost = f"S = {r.cost:.6g}"
        per_dof = f"reduced χ² = {fmt(r.reduced_chi2, 4)}"
    else:  # the robust cost is not a χ² (the fit verdict below tests the plain squares)
        cost = f"S = Σρ(r²) = {r.cost:.6g} ({loss} loss)"
        per_dof = f"Σρ/dof = {fmt(r.reduced_chi2, 4)}"
    out.append(
        f"{cost} over {r.problem.n_residuals} residuals ({len(r.problem.measurements)} measurements); "
        f"{per_dof}; RMS: {rms}"
    )
    rows = []
    for i, name in enumerate(r.names):
        unit = r.unit(name)
        rows.append(
            [
                name,
                _value_cell(unit, r.x[i]),
                "0 (at bound)" if name in r.observability.active_bounds else _std_cell(unit, r.observability.std[i]),
                _value_cell(unit, r.x_initial[i]),
            ]
        )
    out.append("")
    out.append(table(["parameter", "estimate", "σ", "initial"], rows, align="lrrr"))
    out.extend(_active_bounds_text(r))
    out.extend(_far_outside_ranges_text(r))
    out.extend(_observability_text(r.observability, r.problem.params))
    out.extend(_points_text(r.points, r.problem.model))
    worst = r.residuals.worst(max_residuals)
    res_rows = []
    model = r.problem.model
    roles = {role.name: role.lookup for kind in r.residuals.kinds for role in _roles(kind)}
    for row in worst:
        refs = " ".join(_short(model, roles.get(k, ""), str(v)) for k, v in row.refs.items())
        res_rows.append(
            [row.id, row.kind, row.config, refs, " ".join(f"{v:+.3g}" for v in row.residual), f"{row.normalized:.3g}"]
        )
    out.append("")
    out.append(
        table(
            ["id", "kind", "config", "refers to", "residual", "|r|/σ"],
            res_rows,
            align="llllrr",
            title=f"residuals, worst first ({len(r.residuals)} in all):",
        )
    )
    hidden = list(r.run.not_visible)
    if hidden:
        out.append(
            f"warning: {len(hidden)} measurement(s) cannot be made at the solution (the point is behind the camera "
            f"or outside its image, or the ray hits nothing): {', '.join(hidden[:8])}"
            + (" …" if len(hidden) > 8 else "")
        )
    if r.outliers:
        out.append(
            f"{len(r.outliers)} outlier(s) above {r.outlier_threshold:g}σ: "
            + ", ".join(row.id for row in r.outliers[:10])
            + (" …" if len(r.outliers) > 10 else "")
        )
    if r.verdict is not None:
        out.append("")
        out.extend(r.verdict.lines())
    counts: dict[str, int] = {}
    for s in solver.statuses():
        counts[s.label] = counts.get(s.label, 0) + 1
    summary = ", ".join(f"{v} {k}" for k, v in sorted(counts.items(), key=lambda t: -t[1]))
    finite = solver.cost[np.isfinite(solver.cost)]
    same = int(np.sum(np.abs(finite - r.cost) <= 1e-6 * max(r.cost, 1e-12))) if finite.size else 0
    out.append("")
    out.append(
        f"restarts: {len(solver.cost)} ({summary}); best #{solver.best}; {same} reached the best S; "
        f"solved in {r.elapsed:.2f} s"
    )
    if r.run.note:
        out.append(f"restarts chosen: {r.run.note}")
    return "\n".join(out)


def plan_json(a: PlanAnalysis) -> dict[str, Any]:
    units = {n: a.problem.params.info(n).unit for n in a.names}
    return {
        "format": REPORT_FORMAT,
        "kind": "plan",
        "model": a.problem.model.path,
        "plan": a.problem.measurements.path,
        "n_measurements": len(a.problem.measurements),
        "invisible": a.invisible,
        "parameters": _parameters_json(a.names, units, a.x, None, a.observability.std),
        "observable": a.observability.observable_with_priors,
        "rank": a.observability.rank,
        "unobservable": [c.to_json() for c in a.observability.unobservable],
        "observability": _observability_json(a.observability),
        "covariance": _covariance_json(a.names, a.observability.covariance, a.observability.correlation),
        "points": [p.to_json() for p in a.points],
        **({"fit": a.verdict.to_json()} if a.verdict is not None else {}),
        "ok": a.ok,
    }


def plan_text(a: PlanAnalysis) -> str:
    out = [f"plan: {len(a.problem.measurements)} measurements, {a.problem.size} values, {len(a.names)} unknowns"]
    if a.invisible:
        out.append(
            f"warning: {len(a.invisible)} planned measurement(s) cannot be made at these values "
            f"(not counted): {', '.join(a.invisible[:8])}{' …' if len(a.invisible) > 8 else ''}"
        )
    rows = []
    for i, name in enumerate(a.names):
        unit = a.problem.params.info(name).unit
        rows.append([name, _value_cell(unit, a.x[i]), _std_cell(unit, a.observability.std[i])])
    out.append("")
    out.append(table(["parameter", "at", "expected σ"], rows, align="lrr"))
    out.extend(_observability_text(a.observability, a.problem.params))
    out.extend(_points_text(a.points, a.problem.model))
    if a.verdict is not None:
        out.append("")
        out.extend(a.verdict.lines())
    return "\n".join(out)
