"""The library API: calibrate, simulate, analyse a plan, and read the result.

>>> import mbcal
>>> model = mbcal.load_model("models/teleexistence.mdl")                       # doctest: +SKIP
>>> data = mbcal.read_measurements("measurements/room_stereo.csv", model)     # doctest: +SKIP
>>> result = mbcal.calibrate(model, data, estimate=["room.*"], restarts=32)    # doctest: +SKIP
>>> result.values["room.yaw"], result.std["room.yaw"]                          # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal.errors import MbcalError, SolverError
from mbcal.language.model import Model
from mbcal.measurements import get_model
from mbcal.measurements.files import MeasurementSet, measurements_from_records
from mbcal.observability import (
    Observability,
    ObservabilityConfig,
    PointUncertainty,
    analyze,
    point_uncertainty,
    rank_candidates,
    unknown_scales,
)
from mbcal.problem import Problem
from mbcal.solver import LeastSquaresResult, SolverConfig, Status, least_squares, random_starts
from mbcal.units import to_display

__all__ = [
    "calibrate",
    "simulate",
    "observe",
    "CalibrationResult",
    "PlanAnalysis",
    "ResidualRow",
]


@dataclass(frozen=True)
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


def _units(problem: Problem) -> dict[str, str]:
    return {u.name: u.param.unit for u in problem.params.unknowns}


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
    residuals: list[ResidualRow]
    points: list[PointUncertainty]
    cost: float
    rms: dict[str, float]
    elapsed: float
    outlier_threshold: float = 3.0
    info: dict[str, Any] = field(default_factory=dict)

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
        """Converged and every unknown determined."""
        return self.converged and self.observable

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
        rows = [r for r in self.residuals if r.normalized > self.outlier_threshold]
        return sorted(rows, key=lambda r: -r.normalized)

    def display(self, name: str, value: float) -> float:
        return to_display(self.problem.params.info(name).unit, value)

    def unit(self, name: str) -> str:
        return self.problem.params.info(name).unit

    # ---- output ------------------------------------------------------------------------------------

    def to_json(self) -> dict[str, Any]:
        """The report as plain data (schema: docs/report.md)."""
        from mbcal.reporting import result_json

        return result_json(self)

    def summary(self, *, max_residuals: int = 15) -> str:
        """The report as text tables."""
        from mbcal.reporting import result_text

        return result_text(self, max_residuals=max_residuals)

    def write_model(self, path, *, overwrite: bool = True) -> None:
        """Write the model with the estimated values as its nominal values (the input is untouched)."""
        from mbcal.writer import write_calibrated_model

        write_calibrated_model(self, path, overwrite=overwrite)


def _residual_rows(problem: Problem, x: np.ndarray) -> list[ResidualRow]:
    h = problem.predict(x)
    y = problem.y
    r = problem.residual(x)[: problem.size]
    rows = []
    for g in problem.groups:
        s = g.model.size
        for k, i in enumerate(g.members):
            m = problem.measurements.measurements[i]
            sl = slice(g.start + k * s, g.start + (k + 1) * s)
            rows.append(
                ResidualRow(
                    m.id, m.kind, m.config, dict(m.refs), y[sl].copy(), h[sl].copy(), float(np.sqrt(np.sum(r[sl] ** 2)))
                )
            )
    order = {m.id: i for i, m in enumerate(problem.measurements.measurements)}
    rows.sort(key=lambda row: order[row.id])
    return rows


def _rms(problem: Problem, rows: list[ResidualRow]) -> dict[str, float]:
    """RMS of the residuals per kind, in the measurement's units.

    Image points follow OpenCV: √(Σ‖e‖² / number of points), e the 2-D pixel error.
    """
    out: dict[str, float] = {}
    for kind in dict.fromkeys(r.kind for r in rows):
        e = np.array([r.residual for r in rows if r.kind == kind])
        if kind == "image_point":
            out[kind] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        else:
            out[kind] = float(np.sqrt(np.mean(e**2)))
    return out


def _jacobian_split(problem: Problem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    J = problem.jacobian(x)
    return J[: problem.size], J[problem.size :]


def _point_uncertainties(
    problem: Problem, x: np.ndarray, covariance: np.ndarray, points: Sequence[str] | None, camera: str | None
) -> list[PointUncertainty]:
    model = problem.model
    configs = problem.params.configurations
    wanted: dict[tuple[str, str], str | None] = {}
    if points is None:
        for m in problem.measurements:
            if "point" in m.refs:
                wanted.setdefault((m.refs["point"], m.config), m.refs.get("camera"))
    else:
        for p in points:
            full = model.resolve("point", p)
            for cfg in configs:
                wanted.setdefault((full, cfg), None)
    if not wanted:
        return []
    if camera is not None:
        camera = model.resolve("camera", camera)
    idx = np.array([model.point_index(p) for p, _ in wanted], dtype=np.int64)
    cfg_idx = np.array([configs.index(c) for _, c in wanted], dtype=np.int64)
    P, J = problem.point_jacobian(x, cfg_idx, idx)  # (k, 3), (k, 3, n)
    origins = problem.frame_origins(x)
    out = []
    for k, ((name, cfg), cam) in enumerate(wanted.items()):
        cam = camera or cam or (model.cameras[0].name if model.cameras else None)
        eye = None
        if cam is not None:
            eye = origins[configs.index(cfg), model.cameras[model.camera_index(cam)].frame]
        out.append(point_uncertainty(name, cfg, cam, P[k], J[k], covariance, eye))
    return out


def _candidate_rows(problem: Problem, x: np.ndarray, measured_keys: set) -> list[tuple[dict[str, Any], np.ndarray]]:
    """Jacobian rows of every candidate measurement not already made, that can be made."""
    model = problem.model
    kinds = list(model.measures) or problem.measurements.kinds
    records = []
    for kind in kinds:
        try:
            mm = get_model(kind)
        except MbcalError:
            continue
        for rec in mm.candidates(model, list(problem.params.configurations)):
            key = (
                rec["kind"],
                rec.get("config"),
                tuple(sorted((k, v) for k, v in rec.items() if k not in ("kind", "config"))),
            )
            if key not in measured_keys:
                records.append({**rec, "sigma": mm.default_sigma})
    if not records:
        return []
    records = records[:5000]
    plan = measurements_from_records(
        records, model, known=problem.measurements.known, configurations=problem.measurements.configurations
    )
    cand = Problem(model, plan, problem.unknown_names, priors=False)
    visible = cand.visible(x)
    J = cand.jacobian(x)
    out = []
    for g in cand.groups:
        s = g.model.size
        for k, i in enumerate(g.members):
            if not visible[i]:
                continue
            rec = {key: val for key, val in records[i].items() if key != "sigma"}
            out.append((rec, J[g.start + k * s : g.start + (k + 1) * s]))
    return out


def _measured_keys(ms: MeasurementSet) -> set:
    keys = set()
    for m in ms:
        items = {**m.refs, **{k: int(v) if float(v).is_integer() else v for k, v in m.data.items()}}
        keys.add((m.kind, m.config, tuple(sorted(items.items()))))
    return keys


def calibrate(
    model: Model,
    measurements: MeasurementSet,
    estimate: Sequence[str],
    *,
    restarts: int = 16,
    seed: int | None = 0,
    config: SolverConfig | None = None,
    known: Mapping[str, float] | None = None,
    priors: bool = True,
    scale_covariance: bool = False,
    points: Sequence[str] | None = None,
    camera: str | None = None,
    suggest: bool = True,
    observability: ObservabilityConfig | None = None,
    outlier_threshold: float = 3.0,
    initial: Mapping[str, float] | None = None,
    progress: Callable[[str], None] | None = None,
) -> CalibrationResult:
    """Estimate the unknowns from measurements (seed, section 3).

    Parameters
    ----------
    model : Model
    measurements : MeasurementSet
    estimate : sequence of str
        Names or glob patterns of the unknowns.
    restarts : int
        Number of starting points: the first is the nominal value, the others are drawn
        uniformly in each unknown's search range; all run in one compiled, vmapped call and
        the one with the smallest S wins.
    seed : int
        Seed of the random starting points (results are reproducible for a given seed).
    config : SolverConfig
        Tolerances, iteration limit, robust loss.
    known : mapping
        Known values that override the model and the file.
    priors : bool
        Use the model's prior σ of the unknowns.
    scale_covariance : bool
        Multiply the covariance by the reduced χ² (when the σ of the measurements are not trusted).
    points : sequence of str
        Points whose uncertainty to report (default: every measured point).
    camera : str
        Camera whose line of sight splits the point uncertainty (default: the camera each point
        was measured in).
    suggest : bool
        When unobservable, rank candidate measurements that would help.
    initial : mapping
        Starting values of unknowns (``name`` or ``name@config``) for the first restart, e.g. from a
        closed-form solution; the other restarts are drawn in the search ranges.
    """
    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    problem = Problem(model, measurements, estimate, known=known, priors=priors)
    problem.check_ready()
    params = problem.params
    x_init = params.from_dict(dict(initial)) if initial else params.x0
    starts = random_starts(x_init, params.lower, params.upper, restarts, seed)
    config = config or SolverConfig()
    say(f"solving: {params.size} unknowns, {problem.size} residuals, {len(starts)} restarts")
    solved = least_squares(
        problem.residual_function,
        starts,
        args=(problem.y, params.known),
        config=config,
        size=problem.n_residuals,
        cache_key=problem.fingerprint(),
    )
    if solved.best < 0:
        raise SolverError(
            "every restart failed: the residuals are not finite at any starting point "
            "(a point behind a camera? a zero-length axis?)",
            hint="check the model's nominal values and the search ranges",
        )
    x = solved.x_best
    say("analysing observability")
    Jm, Jp = _jacobian_split(problem, x)
    rows = _residual_rows(problem, x)
    cost = solved.cost_best
    m_rows = problem.n_residuals
    provisional_dof = max(m_rows - params.size, 1)
    chi2 = cost / provisional_dof if scale_covariance else 1.0
    obs = analyze(Jm, Jp, params.names, _units(problem), unknown_scales(params), config=observability, chi2_scale=chi2)
    if suggest and not obs.observable:
        say("ranking candidate measurements")
        candidates = _candidate_rows(problem, x, _measured_keys(measurements))
        obs.suggestions = rank_candidates(obs, Jm, Jp, candidates)
    pts = _point_uncertainties(problem, x, obs.covariance, points, camera)
    visible = problem.visible(x)
    not_visible = [m.id for m, v in zip(measurements.measurements, visible) if not v]
    return CalibrationResult(
        problem=problem,
        solver=solved,
        x=x,
        x_initial=x_init,
        observability=obs,
        residuals=rows,
        points=pts,
        cost=cost,
        rms=_rms(problem, rows),
        elapsed=time.perf_counter() - t0,
        outlier_threshold=outlier_threshold,
        info={
            "restarts": restarts,
            "seed": seed,
            "config": config,
            "scale_covariance": scale_covariance,
            "not_visible": not_visible,
        },
    )


def simulate(
    model: Model,
    plan: MeasurementSet,
    truth: Mapping[str, float] | None = None,
    *,
    noise: float = 1.0,
    seed: int | None = 0,
    drop_invisible: bool = False,
) -> MeasurementSet:
    """Synthesise measurements for a plan from given true parameter values.

    Parameters
    ----------
    model : Model
    plan : MeasurementSet
        What to measure (values, if any, are ignored) with each measurement's σ.
    truth : mapping
        True values (SI) of any parameters, ``name`` or ``name@config``; the rest take the
        plan's known values or the model's nominal values.
    noise : float
        Multiplier of each measurement's covariance: 0 gives exact values, 1 the plan's σ.
    seed : int
        Seed of the noise (reproducible).
    drop_invisible : bool
        Leave out measurements that cannot be made (points behind a camera or outside its
        image); otherwise they raise an error.
    """
    truth = dict(truth or {})
    names = list(dict.fromkeys(k.split("@")[0] for k in truth))
    problem = Problem(model, plan, names, priors=False)
    x = problem.params.from_dict({k: v for k, v in truth.items() if k in problem.params.names})
    for key in truth:
        if key not in problem.params.names:
            # A per-configuration parameter set globally: give every copy the value.
            copies = [n for n in problem.params.names if n.split("@")[0] == key]
            for c in copies:
                x[problem.params.names.index(c)] = float(truth[key])
    visible = problem.visible(x)
    if not visible.all():
        bad = [m for m, v in zip(plan.measurements, visible) if not v]
        if not drop_invisible:
            first = bad[0]
            raise SolverError(
                f"{len(bad)} planned measurement(s) cannot be made with these values, e.g. '{first.id}' "
                f"({first.kind} {', '.join(f'{k} {v}' for k, v in first.refs.items())}): "
                "behind the camera, outside the image or hitting nothing",
                first.where,
                hint="drop them from the plan, or pass drop_invisible=True (--drop-invisible)",
            )
        plan = plan.subset(visible)
        problem = Problem(model, plan, names, priors=False)
        x = x  # same unknowns
    h = problem.predict(x)
    rng = np.random.default_rng(seed)
    values = []
    for g in problem.groups:
        s = g.model.size
        for k, i in enumerate(g.members):
            m = plan.measurements[i]
            mean = h[g.start + k * s : g.start + (k + 1) * s]
            if g.model.implicit_value is not None:
                values.append((i, np.full(s, g.model.implicit_value)))
                continue
            e = rng.multivariate_normal(np.zeros(s), m.cov) * np.sqrt(noise) if noise > 0 else np.zeros(s)
            values.append((i, mean + e))
    ordered = [v for _, v in sorted(values, key=lambda t: t[0])]
    return plan.with_values(ordered)


@dataclass
class PlanAnalysis:
    """Is a measurement plan enough? (``mbcal observe``)."""

    problem: Problem
    x: np.ndarray
    observability: Observability
    points: list[PointUncertainty]
    invisible: list[str]

    @property
    def names(self) -> list[str]:
        return self.problem.unknown_names

    @property
    def std(self) -> dict[str, float]:
        return dict(zip(self.names, map(float, self.observability.std)))

    def to_json(self) -> dict[str, Any]:
        from mbcal.reporting import plan_json

        return plan_json(self)

    def summary(self) -> str:
        from mbcal.reporting import plan_text

        return plan_text(self)


def observe(
    model: Model,
    plan: MeasurementSet,
    estimate: Sequence[str],
    *,
    at: Mapping[str, float] | None = None,
    priors: bool = True,
    suggest: bool = True,
    points: Sequence[str] | None = None,
    camera: str | None = None,
    observability: ObservabilityConfig | None = None,
) -> PlanAnalysis:
    """Analyse a plan before measuring: rank, σ per unknown, unobservable combinations, suggestions.

    The Jacobian is taken at the nominal values (or ``at``).
    """
    problem = Problem(model, plan, estimate, priors=priors)
    if problem.params.size == 0:
        raise SolverError("nothing to estimate: name the unknowns (--estimate NAME|GLOB)")
    x = problem.params.from_dict(dict(at or {})) if at else problem.params.x0
    visible = problem.visible(x)
    Jm, Jp = _jacobian_split(problem, x)
    Jm = Jm.copy()
    for g in problem.groups:  # invisible measurements contribute nothing
        s = g.model.size
        for k, i in enumerate(g.members):
            if not visible[i]:
                Jm[g.start + k * s : g.start + (k + 1) * s] = 0.0
    obs = analyze(Jm, Jp, problem.params.names, _units(problem), unknown_scales(problem.params), config=observability)
    if suggest and not obs.observable:
        obs.suggestions = rank_candidates(obs, Jm, Jp, _candidate_rows(problem, x, _measured_keys(plan)))
    pts = _point_uncertainties(problem, x, obs.covariance, points, camera)
    invisible = [m.id for m, v in zip(plan.measurements, visible) if not v]
    return PlanAnalysis(problem, x, obs, pts, invisible)
