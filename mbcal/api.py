"""The library API: calibrate, simulate, analyse a plan, and read the result.

>>> import mbcal
>>> model = mbcal.load_model("models/teleexistence.mdl")                       # doctest: +SKIP
>>> data = mbcal.read_measurements("measurements/room_stereo.csv", model)     # doctest: +SKIP
>>> result = mbcal.calibrate(model, data, estimate=["room.*"], restarts=32)    # doctest: +SKIP
>>> result.values["room.yaw"], result.std["room.yaw"]                          # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import functools
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, Protocol

import numpy as np

from mbcal._jax import in_float64, jax, release_memory
from mbcal.errors import MdlError, SolverError
from mbcal.errors import suggest as suggest_name
from mbcal.fit import FitConfig, assess_fit, assess_plan, distinct_minima
from mbcal.language.check import check_at_nominal
from mbcal.language.model import Model
from mbcal.measurements.registry import call_model, get_model
from mbcal.measurements.sets import MeasurementSet, measurements_from_records
from mbcal.observability import (
    Observability,
    ObservabilityConfig,
    PointLabels,
    PointUncertainty,
    analyze,
    point_uncertainties,
    rank_candidates,
    unknown_scales,
)
from mbcal.problem import Problem
from mbcal.results import CalibrationResult, DeferredPoints, PlanAnalysis, ResidualRow, ResidualRows, RunInfo
from mbcal.solver import (  # noqa: F401  (the size limits: mbcal.api's names since they were made)
    MAX_DENSE_UNKNOWNS,
    MAX_RESTARTS,
    MAX_SOLVER_BYTES,
    SolverConfig,
    check_size,
    least_squares,
    random_starts,
)
from mbcal.structured import (
    DENSE_ANALYSIS_ENTRIES,
    BlockCovariance,
    Structure,
    StructuredLinear,
    block_point_uncertainties,
    compressed_jacobian,
    expand_jacobian,
    held_columns,
    joint_from_dense,
    least_squares_structured,
    observability_structured,
    pays,
    rank_candidates_structured,
    square_root_information,
    structure_of,
)
from mbcal.units import ANGLE, at_least, whole

__all__ = [
    "calibrate",
    "simulate",
    "observe",
    "CalibrateOptions",
    "CalibrationResult",
    "FitConfig",
    "MAX_DENSE_UNKNOWNS",
    "MAX_RESTARTS",
    "MAX_SOLVER_BYTES",
    "PlanAnalysis",
    "ResidualRow",
    "ResidualRows",
    "RunInfo",
]


@dataclass(frozen=True)
class CalibrateOptions:
    """How :func:`calibrate` runs.  Every field has the default the CLI uses too.

    ``calibrate(model, data, estimate, restarts=32)`` is shorthand for
    ``calibrate(model, data, estimate, CalibrateOptions(restarts=32))``.
    """

    restarts: int = 16
    """Number of starting points: the first is the nominal value (or ``initial``), the others are
    drawn uniformly in each unknown's search range; all run in one compiled, vmapped call and the
    one with the smallest S wins."""
    seed: int | None = 0
    """Seed of the random starting points (results are reproducible for a given seed)."""
    config: SolverConfig | None = None
    """Tolerances, iteration limit, robust loss (default: :class:`SolverConfig`)."""
    known: Mapping[str, float] | None = None
    """Known values (SI) that override the model and the measurement file.  A parameter that is
    also estimated is not held: its value here is where its first restart starts (as the model's
    nominal value would be); to hold it, leave it out of ``estimate``."""
    priors: bool = True
    """Use the model's prior σ of the unknowns."""
    scale_covariance: bool = False
    """Multiply the covariance by the reduced χ² (when the σ of the measurements are not trusted).
    Not done without redundancy (no more residuals than free unknowns — those not held at a hard
    limit: the residuals then say nothing about the noise); the result's ``run.scale_covariance``
    says whether it was."""
    points: Sequence[str] | None = None
    """Points whose uncertainty to report (default: every measured point)."""
    camera: str | None = None
    """Camera whose line of sight splits the point uncertainty (default: the camera each point
    was measured in)."""
    suggest: bool = True
    """When something is unobservable, rank candidate measurements that would help."""
    observability: ObservabilityConfig | None = None
    """Thresholds of the observability analysis."""
    outlier_threshold: float = 3.0
    """Measurements whose normalised residual exceeds this many σ are listed as outliers."""
    initial: Mapping[str, float] | None = None
    """Starting values of unknowns (``name`` or ``name@config``) for the first restart, e.g. from a
    closed-form solution."""
    progress: Callable[[str], None] | None = None
    """Called with a short message at each step (compiling, analysing, ...)."""
    fit: FitConfig | None = None
    """Thresholds of the fit verdict: the χ² test's p-value threshold (default 0.001), the largest
    condition number (see :class:`mbcal.fit.FitConfig` and docs/report.md)."""
    accept_poor_fit: bool = False
    """Count an inconsistent or weakly determined fit as ``ok`` (the verdict is still reported):
    for scripts that want the estimate anyway (``--accept-poor-fit``)."""
    analysis: str = "auto"
    """How a problem solved by the Schur complement is analysed after the solve (issue 15):
    ``auto`` densely (the full Jacobian) up to :data:`mbcal.structured.DENSE_ANALYSIS_ENTRIES`
    entries, from its blocks beyond; ``structured`` from its blocks always; ``dense`` densely always.
    The blocks give the same report without any n × n or m × n matrix (docs/scale.md)."""

    def __post_init__(self) -> None:
        # Checked here, where the caller's mistake is still theirs: deep in the solver a float count
        # or a dict for a config was a NumPy TypeError or an AttributeError naming mbcal's code.
        if not whole(self.restarts, -(2**63)):  # the count itself: check_size
            raise SolverError(f"restarts must be a whole number ≥ 1, got {self.restarts!r}")
        _check_seed(self.seed)
        for name, kind in (("config", SolverConfig), ("fit", FitConfig), ("observability", ObservabilityConfig)):
            value = getattr(self, name)
            if value is not None and not isinstance(value, kind):
                raise SolverError(f"{name} must be a {kind.__name__} (or None), got {value!r}")
        for name in ("known", "initial"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, Mapping):
                raise SolverError(f"{name} must be a mapping of parameter names to values, got {value!r}")
        if not at_least(self.outlier_threshold, 0.0):
            raise SolverError(f"outlier_threshold must be a finite number of σ ≥ 0, got {self.outlier_threshold!r}")
        _check_analysis(self.analysis)

    def updated(self, changes: Mapping[str, Any]) -> CalibrateOptions:
        """A copy with some fields changed; an unknown field name is an error that lists the fields."""
        names = [f.name for f in fields(self)]
        for key in changes:
            if key not in names:
                hint = suggest_name(key, names)
                raise TypeError(
                    f"calibrate() got an unexpected option '{key}'"
                    + (f"; {hint}" if hint else "")
                    + f" (options: {', '.join(names)})"
                )
        return replace(self, **changes)


def _check_seed(seed: Any) -> None:
    """A seed of the random starts or of the noise: NumPy's generators take a whole number ≥ 0."""
    if seed is not None and not whole(seed, 0):
        raise SolverError(f"seed must be a whole number ≥ 0 or None, got {seed!r}")


def _units(problem: Problem) -> dict[str, str]:
    return {u.name: u.param.unit for u in problem.params.unknowns}


def _residual_rows(problem: Problem, x: np.ndarray, residual: np.ndarray) -> ResidualRows:
    """Each measurement at x; ``residual`` is the whitened residual at x (measurements, then priors).

    Per kind as arrays (issue 16): a row is made only when it is read.  The predicted values come
    from the residual, r = W (h − y) with W the whitening (1/σ, or the inverse Cholesky factor of
    the covariance), instead of running the model again."""
    y = problem.y
    r = residual[: problem.size]
    h = None
    kinds = {}
    norms = []
    for g in problem.groups:
        s = g.model.size
        part = slice(g.start, g.start + g.rows)
        Y, R = y[part].reshape(-1, s), r[part].reshape(-1, s)
        W = np.asarray(g.whiten)
        if not (np.all(np.isfinite(W)) and (np.all(W != 0) if g.diagonal else True)):
            h = problem.predict(x) if h is None else h  # a zero or infinite weight: the model's own h
            H = h[part].reshape(-1, s).copy()
        elif g.diagonal:
            H = Y + R / W
        else:
            H = Y + np.linalg.solve(W, R[:, :, None])[:, :, 0]
        kinds[g.model.kind] = (g.members, Y.copy(), H)
        norms.append((g.members, np.sqrt(np.sum(R**2, axis=1))))
    rows = ResidualRows(problem.measurements.measurements, kinds)
    for members, norm in norms:
        rows.normalized[members] = norm
    return rows


def _rms(problem: Problem, rows: ResidualRows) -> dict[str, float]:
    """RMS of the residuals per kind, in the measurement's units.

    Image points follow OpenCV: √(Σ‖e‖² / number of points), e the 2-D pixel error.
    """
    out: dict[str, float] = {}
    for kind in rows.kinds:
        _members, measured, predicted = rows.kind(kind)
        e = measured - predicted
        if kind == "image_point":
            out[kind] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        else:
            out[kind] = float(np.sqrt(np.mean(e**2)))
    return out


def _jacobian_split(problem: Problem, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    J = problem.jacobian(x)
    return J[: problem.size], J[problem.size :]


def _point_uncertainties(
    problem: Problem,
    x: np.ndarray,
    covariance: np.ndarray | BlockCovariance,
    points: Sequence[str] | None,
    camera: str | None,
) -> Sequence[PointUncertainty]:
    model = problem.model
    configs = problem.params.configurations
    C = len(configs)
    if points is None:  # every (point, configuration) measured, in the set's order; the first one's camera
        found = []
        for g in problem.groups:
            if "point" in g.batch.refs:
                cam = g.batch.refs["camera"] if "camera" in g.batch.refs else np.full(len(g.members), -1)
                found.append((g.members, g.batch.refs["point"], g.batch.config, cam))
        if not found:
            return []
        order, idx, cfg_idx, cam_idx = (np.concatenate(parts) for parts in zip(*found))
        key = idx * C + cfg_idx
        _, first = np.unique(key, return_index=True)
        first = first[np.argsort(order[first], kind="stable")]  # first appearance in the set
        idx, cfg_idx, cam_idx = idx[first], cfg_idx[first], cam_idx[first]
    else:
        full = dict.fromkeys(model.resolve("point", p) for p in points)
        idx = np.repeat(np.array([model.point_index(p) for p in full], dtype=np.int64), C)
        cfg_idx = np.tile(np.arange(C), len(idx) // C)
        cam_idx = np.full(len(idx), -1)
        if not len(idx):
            return []
    if camera is not None:
        cam_idx = np.full(len(idx), model.camera_index(model.resolve("camera", camera)))
    elif model.cameras:
        cam_idx = np.where(cam_idx < 0, 0, cam_idx)  # no camera named: the model's first one
    origins = problem.frame_origins(x)
    eyes = np.full((len(idx), 3), np.nan)  # NaN: no line of sight (a model without cameras)
    seen = cam_idx >= 0
    if seen.any():
        frame_of = np.array([c.frame for c in model.cameras], dtype=np.int64)
        eyes[seen] = origins[cfg_idx[seen], frame_of[cam_idx[seen]]]
    point_names = [p.name for p in model.points]
    camera_names = [c.name for c in model.cameras]
    items = PointLabels(point_names, idx, configs, cfg_idx, camera_names, cam_idx)
    if isinstance(covariance, BlockCovariance):  # a structured problem's: each point from its block (issue 15)
        return covariance.point_uncertainties(problem, x, cfg_idx, idx, items, eyes)
    structure = _structure_of(problem) if C >= 2 else None
    if structure is not None:  # a block per configuration: the points' Jacobians need nb + ks columns, not n
        joint = joint_from_dense(structure, covariance)
        return block_point_uncertainties(problem, structure, joint, x, cfg_idx, idx, items, eyes)
    P, J = problem.point_jacobian(x, cfg_idx, idx)  # (k, 3), (k, 3, n)
    return point_uncertainties(items, P, J, covariance, eyes)


def _candidate_rows(problem: Problem, x: np.ndarray, measured_keys: set) -> list[tuple[dict[str, Any], np.ndarray]]:
    """Jacobian rows of every candidate measurement not already made, that can be made."""
    found = _candidates(problem, measured_keys)
    if found is None:
        return []
    records, cand = found
    visible = cand.visible(x)
    J = cand.jacobian(x)
    return [
        ({key: val for key, val in record.items() if key != "sigma"}, J[rows])
        for record, rows, seen in zip(records, cand.measurement_rows, visible)
        if seen
    ]


def _candidate_rows_by_blocks(
    problem: Problem, structure: Structure, x: np.ndarray, measured_keys: set
) -> list[tuple[dict[str, Any], np.ndarray, int]]:
    """:func:`_candidate_rows` compressed (issue 15): each candidate's rows over its configuration's
    block and the shared unknowns (nb + ks columns, not n), and that block."""
    found = _candidates(problem, measured_keys)
    if found is None:
        return []
    records, cand = found
    own = structure_of(cand)  # the same unknowns: the same blocks, the candidates' rows their own
    if own is None or not np.array_equal(own.blocks, structure.blocks):
        return []
    visible = cand.visible(x)
    _, Jc = compressed_jacobian(cand.residual_function, x, own, (np.nan_to_num(cand.y), cand.params.known))
    return [
        ({key: val for key, val in record.items() if key != "sigma"}, Jc[rows], int(own.row_block[rows.start]))
        for record, rows, seen in zip(records, cand.measurement_rows, visible)
        if seen
    ]


def _candidates(problem: Problem, measured_keys: set) -> tuple[list[dict[str, Any]], Problem] | None:
    """The records of the candidate measurements not already made (at most 5,000) and the problem
    they form (None when there are none)."""
    model = problem.model
    kinds = list(model.measures) or problem.measurements.kinds
    records = []
    for kind in kinds:
        mm = get_model(kind)  # every kind is installed: Problem checked the model's, the set its own
        for rec in call_model(mm, "candidates", model, list(problem.params.configurations)):
            key = (
                rec["kind"],
                rec.get("config"),
                tuple(sorted((k, v) for k, v in rec.items() if k not in ("kind", "config"))),
            )
            if key not in measured_keys:
                records.append({**rec, "sigma": mm.default_sigma})
    if not records:
        return None
    records = records[:5000]
    # Every configuration of the problem, in its order (those without a candidate too: the
    # unknowns name them), so that the candidates' problem has the same unknowns at the same places.
    given = problem.measurements.configurations
    configurations = {c: given.get(c, {}) for c in problem.params.configurations}
    plan = measurements_from_records(records, model, known=problem.measurements.known, configurations=configurations)
    # the caller's known values too (--set): the candidates are predicted with the values of the fit
    return records, Problem(model, plan, problem.unknown_names, known=problem.known_given, priors=False)


def _measured_keys(ms: MeasurementSet) -> set:
    keys = set()
    for m in ms:
        items = {**m.refs, **{k: int(v) if float(v).is_integer() else v for k, v in m.data.items()}}
        keys.add((m.kind, m.config, tuple(sorted(items.items()))))
    return keys


_STRUCTURES: weakref.WeakKeyDictionary[Problem, Structure | None] = weakref.WeakKeyDictionary()


def _structure_of(problem: Problem) -> Structure | None:
    """:func:`mbcal.structured.structure_of`, once per problem (the solve and the point
    uncertainties both read it: ~0.2 ms each for 13 views, issue 16)."""
    if problem not in _STRUCTURES:
        _STRUCTURES[problem] = structure_of(problem)
    return _STRUCTURES[problem]


def _structure(problem: Problem, config: SolverConfig) -> Structure | None:
    """Issue 15: the block structure to solve by the Schur complement, or None for the dense solver.

    The rule (``SolverConfig.structure``): ``dense`` never; ``structured`` always (an error when
    the problem has no block structure); ``auto`` when :func:`mbcal.structured.pays`: at least 8
    configurations with unknowns of their own (board poses), which outnumber the shared ones.
    Hard bounds do not matter: both solvers take them.
    """
    if config.structure == "dense":
        return None
    structure = _structure_of(problem)
    if config.structure == "structured" and structure is None:
        why = "has no configurations with unknowns of their own"
        raise SolverError(f"the structured solver cannot solve this problem: it {why}", hint="use structure='dense'")
    if structure is None or not (config.structure == "structured" or pays(structure)):
        return None
    return structure


def _check_analysis(analysis: str) -> None:
    if analysis not in ("auto", "dense", "structured"):
        raise SolverError(f"analysis must be 'auto', 'dense' or 'structured', got '{analysis}'")


# The fit verdict names untested measurements (those that alone determine part of the unknowns) of
# every measurement when J has at most this many entries (an SVD of it: ~1 ms); beyond, of the
# measurements of configurations whose rows are at most twice their own unknowns — where one can
# alone fix a direction — which a camera calibration of full board views has none of (issue 16).
_LEVERAGE_ENTRIES = 20_000


def _leverage_tested(problem: Problem, structure: Structure | None) -> bool | list[int]:
    """What :func:`mbcal.fit.assess_fit` tests for untested measurements (its ``leverage``)."""
    if problem.n_residuals * problem.params.size <= _LEVERAGE_ENTRIES or structure is None:
        return True
    rows = structure.row_block[: problem.size]
    counts = np.bincount(rows, minlength=structure.n_blocks)
    sparse = counts <= 2 * structure.nb
    blocks = problem.row_blocks
    has_rows = blocks.sizes > 0
    tested = np.zeros(len(blocks), dtype=bool)
    tested[has_rows] = sparse[rows[blocks.starts[has_rows]]]
    return np.nonzero(tested)[0].tolist()


def _other_solutions(problem: Problem, solved: Any, obs: Any, chi2: float) -> list:
    """The fit verdict's other solutions as good as the estimate (:func:`mbcal.fit.distinct_minima`):
    angles known by their dimension (radians written as plain numbers too)."""
    params = problem.params
    return distinct_minima(
        solved,
        obs,
        _units(problem),
        local=problem.local,
        scale=chi2,
        ranges=(params.lower, params.upper),
        angles=[params.info(name).given_dim == ANGLE for name in params.names],
    )


def _analysed_by_blocks(structure: Structure | None, analysis: str) -> bool:
    """Whether the report of a structured solve is computed from the blocks (``CalibrateOptions.analysis``)."""
    _check_analysis(analysis)
    if structure is None or analysis == "dense":
        return False
    return analysis == "structured" or structure.m * structure.n > DENSE_ANALYSIS_ENTRIES


@in_float64
def calibrate(
    model: Model,
    measurements: MeasurementSet,
    estimate: Sequence[str],
    options: CalibrateOptions | None = None,
    **changes: Any,
) -> CalibrationResult:
    """Estimate the unknowns from measurements (seed, section 3).

    Parameters
    ----------
    model : Model
    measurements : MeasurementSet
    estimate : sequence of str
        Names or glob patterns of the unknowns.
    options : CalibrateOptions, optional
        Restarts, seed, solver settings, known values, priors, ... (see :class:`CalibrateOptions`).
    **changes
        Any field of :class:`CalibrateOptions` by name, overriding ``options``:
        ``calibrate(model, data, ["room.*"], restarts=32, seed=1)``.
    """
    o = (options or CalibrateOptions()).updated(changes)
    restarts, seed, config, known, priors = o.restarts, o.seed, o.config, o.known, o.priors
    scale_covariance, suggest = o.scale_covariance, o.suggest
    observability, initial, progress = o.observability, o.initial, o.progress
    t0 = time.perf_counter()
    say = progress or (lambda _msg: None)
    check_size(restarts)
    _check_analysis(o.analysis)
    problem = Problem(model, measurements, estimate, known=known, priors=priors)
    problem.check_ready()
    params = problem.params
    config = config or SolverConfig()
    structure = _structure(problem, config)  # issue 15: the Schur complement when it pays
    if structure is None:
        check_size(restarts, params.size, problem.n_residuals)
    x_init = params.from_dict(dict(initial)) if initial else params.x0
    starts = random_starts(x_init, params.lower, params.upper, restarts, seed, limits=params.bounds)
    say(f"solving: {params.size} unknowns, {problem.size} residuals, {len(starts)} restarts")
    args = (problem.y, params.known)
    analysis = _load_analysis_programs(problem, structure, starts[0], args)
    try:
        if structure is not None:
            solved = least_squares_structured(
                problem.residual_function,
                starts,
                structure,
                args=args,
                config=config,
                local=problem.local,
                cache_key=problem.fingerprint(),  # issue 16: a second process does not trace it again
                bounds=params.bounds,  # hard limits, projected steps by blocks (None: none)
            )
        else:
            solved = least_squares(
                problem.residual_function,
                starts,
                args=args,
                config=config,
                size=problem.n_residuals,
                cache_key=problem.fingerprint(),
                bounds=params.bounds,  # hard limits (None: none); issue 14
                local=problem.local,  # rotation steps for roll-pitch-yaw orientations (None: none)
            )
    except BaseException as err:
        if not isinstance(err, KeyboardInterrupt):  # interrupted, it does not wait for the (daemon) thread
            analysis.join()  # a failed solve too: nothing of this call runs on after it
        raise
    analysis.join()
    if solved.best < 0:
        first, where = _first_nonfinite(problem, x_init)
        raise SolverError(
            "every restart failed: the residuals are not finite at any starting point "
            "(a point behind a camera? a zero-length axis? values or σ so far apart that r² overflows?)" + first,
            where,
            hint="check the model's nominal values, the search ranges and the measurements' magnitudes",
        )
    x = solved.x_best
    say("analysing observability")
    cost = solved.cost_best
    m_rows = problem.n_residuals
    # the free unknowns: one held at a hard limit takes no degree of freedom (as in the fit verdict)
    free = params.size - int(np.count_nonzero(solved.active_best))
    provisional_dof = m_rows - free
    if scale_covariance and provisional_dof <= 0:
        # No redundancy: the residuals say nothing about the noise's scale (S is ~0 at an exact
        # fit, and scaling by it shrank every σ to ~0 under a "well determined" verdict).  The
        # stated σ stand, and the run records that nothing was scaled.
        scale_covariance = False
        o = o.updated({"scale_covariance": False})
    chi2 = cost / provisional_dof if scale_covariance else 1.0
    if _analysed_by_blocks(structure, o.analysis):
        assert structure is not None
        return _calibrate_by_blocks(problem, structure, solved, x, x_init, chi2, o, t0, say)
    # once: the observability analysis and the fit verdict share it (structured: from nb + ks tangents)
    dense: Callable[[], np.ndarray]  # the m × n Jacobian (structured: scattered only when asked for)
    if structure is None:
        r, J = problem.residual_and_jacobian(x)
        dense = lambda: J  # noqa: E731
    else:
        r, Jc = compressed_jacobian(problem.residual_function, x, structure, args, cache_key=problem.fingerprint())
        dense = functools.cache(lambda: expand_jacobian(Jc, structure))
    Jp = dense()[problem.size :] if structure is None else expand_jacobian(Jc[problem.size :], structure, problem.size)
    rows = _residual_rows(problem, x, r)
    obs = analyze(
        # structured: an n × n R with RᵀR = JmᵀJm (same spectrum), not the m × n Jacobian (issue 15)
        J[: problem.size]
        if structure is None
        else square_root_information(Jc[: problem.size], structure.row_block[: problem.size], structure),
        Jp,
        params.names,
        _units(problem),
        unknown_scales(params),
        config=observability,
        chi2_scale=chi2,
        active=solved.active_best,  # unknowns held at an active hard bound
    )
    obs.n_values = problem.size  # the measured values (R above has n rows)
    if suggest and not obs.observable:
        say("ranking candidate measurements")
        candidates = _candidate_rows(problem, x, _measured_keys(measurements))
        obs.suggestions = rank_candidates(obs, dense()[: problem.size], Jp, candidates)
    say("judging the fit")
    verdict = assess_fit(
        problem,
        r,
        dense,  # called only when the fit is not consistent (issue 16)
        obs,
        loss=str(config.loss),
        config=o.fit,
        observability=observability,
        accept=o.accept_poor_fit,
        ambiguous=_other_solutions(problem, solved, obs, chi2),
        leverage=_leverage_tested(problem, structure),
    )
    return _result(problem, solved, x, x_init, obs, rows, verdict, o, config, t0)


# The analysis programs are loaded beside the solve up to this many values in the Jacobian they
# compute at a start (m × n, or m × (nb + ks) by blocks; 32 MB of float64): beyond it a solve takes
# far longer than their load, and their run at the start would add to the solve's peak memory.
_LOAD_BESIDE_VALUES = 4_000_000


def _jax_set_here() -> bool:
    """Whether JAX settings that a thread does not inherit are in force (``with
    jax.default_device(...)``, ``jax.disable_jit()``, NaN/Inf debugging): the programs are then
    not loaded in a thread, which would load them for other settings."""
    # jax.config's attributes give the value in force in this thread (False or None: not set)
    names = ("jax_disable_jit", "jax_debug_nans", "jax_debug_infs", "jax_default_device")
    return any(getattr(jax.config, name) not in (None, False) for name in names)


class _Started(Protocol):
    def join(self) -> None: ...


class _Nothing:
    def join(self) -> None:
        pass


def _load_analysis_programs(problem: Problem, structure: Structure | None, x: np.ndarray, args: tuple) -> _Started:
    """Start loading (or tracing and compiling) the programs the analysis runs after the solve —
    r and J (or the compressed J) and the visibility — in a thread, while the solver's own
    program loads and runs: XLA reads, compiles and runs programs without holding Python's lock,
    so the two overlap (issue 16, measured on 2 cores: a warm ``mbcal calibrate-camera`` of 13
    views 0.97–1.01 → 0.93–0.97 s, an empty cache's 4.16 → 3.85 s).  They are run once at ``x``
    (a start) to be loaded; nothing of that run is kept.  Only the first time a problem of this
    structure is analysed in the process (later, they are loaded) and up to
    :data:`_LOAD_BESIDE_VALUES`.  The caller joins before the analysis: a program asked for while
    the thread still builds it would be built twice.  An error there is left for the analysis to
    raise where it belongs."""
    width = problem.params.size if structure is None else structure.nb + structure.ks
    if problem.n_residuals * width > _LOAD_BESIDE_VALUES or _jax_set_here():
        return _Nothing()
    if not problem.first_analysis():
        return _Nothing()
    if structure is not None:
        structure.arrays()  # built once here, not by both threads at the same time

    @in_float64  # a thread does not inherit calibrate's float64 (mbcal._jax.float64)
    def load() -> None:
        try:
            if structure is None:
                problem.residual_and_jacobian(x)
            else:
                compressed_jacobian(problem.residual_function, x, structure, args, cache_key=problem.fingerprint())
            problem.visible(x)
        except Exception:  # the analysis runs them again and reports what is wrong there
            pass

    thread = threading.Thread(target=load, name="mbcal-analysis-programs", daemon=True)
    thread.start()
    return thread


def _first_nonfinite(problem: Problem, x: np.ndarray) -> tuple[str, Any]:
    """When every restart failed: the measurements whose residual is not finite at the initial
    values (a value of 1e308 px overflows r²), the first by its id and where the file gives it —
    the rule that bad input is located — or ("", None) when the residuals there are finite."""
    try:
        with np.errstate(all="ignore"):
            r = np.asarray(problem.residual(x), dtype=float)
    except Exception:  # the failure the caller reports already; this only adds a location
        return "", None
    with np.errstate(over="ignore", invalid="ignore"):
        bad_rows = np.nonzero(~np.isfinite(r[: problem.size] ** 2))[0]
    if bad_rows.size == 0:
        return "", None
    ms = problem.measurements.measurements
    bad = list(dict.fromkeys(problem.row_measurement[bad_rows].tolist()))
    first = ms[bad[0]]
    return (
        f"; at the initial values {len(bad)} measurement(s) have a residual that is not finite, the first "
        f"'{first.id}' (value {np.asarray(first.value).tolist() if first.value is not None else None})",
        first.where,
    )


def _estimate_breaks_model(problem: Problem, x: np.ndarray) -> str | None:
    """Where the estimate breaks a rule of the model that the loader checks at the nominal values
    (a focal length or a shape's size not positive: :func:`mbcal.language.check.check_at_nominal`,
    signs only — the residuals were finite), in every configuration: ``file:line:col: message``,
    else None."""
    model = problem.model
    if not (model.cameras or model.shapes) or problem.params.size == 0:
        return None
    rows = np.unique(problem.params.X(np.asarray(x, dtype=float)), axis=0)
    for X in rows:
        try:
            check_at_nominal(model, X, where="at the estimate", finite=False)
        except MdlError as err:
            return f"{err.span}: {err.message}" if err.span is not None else err.message
    return None


def _result(
    problem: Problem,
    solved: Any,
    x: np.ndarray,
    x_init: np.ndarray,
    obs: Observability,
    rows: ResidualRows,
    verdict: Any,
    o: CalibrateOptions,
    config: SolverConfig,
    t0: float,
) -> CalibrationResult:
    """The result of a calibration, dense or from the blocks: point uncertainties (computed when
    first read; the names asked for are checked now), visibility, timing."""
    model = problem.model
    for p in o.points or ():
        model.resolve("point", p)
    if o.camera is not None:
        model.resolve("camera", o.camera)
    x_at, covariance = np.array(x), obs.covariance
    pts = DeferredPoints(lambda: _point_uncertainties(problem, x_at, covariance, o.points, o.camera))
    visible = problem.visible(x)
    not_visible = [m.id for m, v in zip(problem.measurements.measurements, visible) if not v]
    if verdict is not None and not (solved.best >= 0 and solved.status_best.converged):
        # the verdict judges a minimum: without one it must not read "consistent and well determined"
        verdict = dataclasses.replace(verdict, not_converged=solved.status_best.label)
    broken = _estimate_breaks_model(problem, x) if verdict is not None else None
    if broken is not None:
        verdict = dataclasses.replace(verdict, invalid_estimate=broken)
    return CalibrationResult(
        problem=problem,
        solver=solved,
        x=x,
        x_initial=x_init,
        observability=obs,
        residuals=rows,
        points=pts,
        cost=solved.cost_best,
        rms=_rms(problem, rows),
        elapsed=time.perf_counter() - t0,
        outlier_threshold=o.outlier_threshold,
        run=RunInfo(o.restarts, o.seed, config, o.scale_covariance, tuple(not_visible)),
        verdict=verdict,
    )


def _calibrate_by_blocks(
    problem: Problem,
    structure: Structure,
    solved: Any,
    x: np.ndarray,
    x_init: np.ndarray,
    chi2: float,
    o: CalibrateOptions,
    t0: float,
    say: Callable[[str], None],
) -> CalibrationResult:
    """The report of a structured solve from its blocks (issue 15): the same observability analysis,
    fit verdict and point uncertainties as the dense path, from the compressed Jacobian (m × (nb + ks))
    — nothing of size n × n or m × n.  Candidate measurements are ranked from their compressed
    Jacobians (:func:`mbcal.structured.rank_candidates_structured`: the dense ranking's scores)."""
    params = problem.params
    r, Jc = compressed_jacobian(
        problem.residual_function, x, structure, (problem.y, params.known), cache_key=problem.fingerprint()
    )
    rows = _residual_rows(problem, x, r)
    obs = observability_structured(
        problem,
        structure,
        Jc,
        names=params.names,
        units=_units(problem),
        scales=unknown_scales(params),
        config=o.observability,
        chi2_scale=chi2,
        active=solved.active_best,  # unknowns held at an active hard bound
    )
    if o.suggest and not obs.observable:
        say("ranking candidate measurements")
        candidates = _candidate_rows_by_blocks(problem, structure, x, _measured_keys(problem.measurements))
        obs.suggestions = rank_candidates_structured(obs, structure, Jc, candidates)
    held = solved.active_best != 0
    if held.any():  # held unknowns are not refitted (as the dense verdict zeroes their columns)
        Jc = held_columns(structure, Jc, held)
    say("judging the fit")
    config = o.config or SolverConfig()
    verdict = assess_fit(
        problem,
        r,
        None,
        obs,
        loss=str(config.loss),
        config=o.fit,
        observability=o.observability,
        accept=o.accept_poor_fit,
        linearize=lambda kept: StructuredLinear(structure, r, Jc, kept),
        leverage=_leverage_tested(problem, structure),
        ambiguous=_other_solutions(problem, solved, obs, chi2),
    )
    return _result(problem, solved, x, x_init, obs, rows, verdict, o, config, t0)


@in_float64
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
        Multiplier of each measurement's σ: 0 gives exact values, 1 the plan's σ, 3 three times
        it (the covariance times 9).  Before 2026-11-25 it multiplied the covariance (σ × √noise),
        while the command line's ``--noise`` and this function's own error message called it a
        multiplier of σ; 0 and 1 give the same values as then.
    seed : int
        Seed of the noise (reproducible).
    drop_invisible : bool
        Leave out measurements that cannot be made (points behind a camera or outside its
        image); otherwise they raise an error.
    """
    truth = dict(truth or {})
    if not at_least(noise, 0.0):
        raise SolverError(f"noise must be a finite number ≥ 0 (a multiplier of each σ), got {noise!r}")
    noise = float(noise)
    _check_seed(seed)
    names = list(dict.fromkeys(str(k).split("@")[0] for k in truth))
    problem = Problem(model, plan, names, priors=False)
    x = problem.params.from_dict({k: v for k, v in truth.items() if k in problem.params.names})
    for key in truth:
        if key not in problem.params.names:
            # A per-configuration parameter set globally: give every copy the value.
            copies = [n for n in problem.params.names if n.split("@")[0] == key]
            if not copies:  # name@config of no configuration's copy: an error, not the nominal value
                problem.params.from_dict({key: truth[key]})
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
    # h from the same program run as the visibility (Problem keeps the last x's values): no second
    # problem for the visible ones, no second compile, ~100 MB less at 100,000 points (issue 15)
    h = problem.predict(x)
    rng = np.random.default_rng(seed)
    values: list[np.ndarray] = [np.zeros(0)] * len(plan.measurements)
    for g in problem.groups:  # group by group: the order of the noise draws (reproducible seeds)
        s = g.model.size
        for i in g.members[visible[g.members]].tolist():
            rows = problem.measurement_rows[i]
            if g.model.implicit_value is not None:
                values[i] = np.full(s, g.model.implicit_value)
                continue
            m = plan.measurements[i]
            e = rng.multivariate_normal(np.zeros(s), m.cov) * noise if noise > 0 else np.zeros(s)
            values[i] = h[rows] + e
    if not visible.all():
        plan = plan.subset(visible)
        values = [v for v, keep in zip(values, visible) if keep]
    out = plan.with_values(values)
    rows = problem.size
    del problem, h, values
    release_memory(64 * rows, collect=True)  # the simulation's temporaries (issue 15)
    return out


@in_float64
def observe(
    model: Model,
    plan: MeasurementSet,
    estimate: Sequence[str],
    *,
    at: Mapping[str, float] | None = None,
    known: Mapping[str, float] | None = None,
    priors: bool = True,
    suggest: bool = True,
    points: Sequence[str] | None = None,
    camera: str | None = None,
    observability: ObservabilityConfig | None = None,
    fit: FitConfig | None = None,
    accept_poor_fit: bool = False,
) -> PlanAnalysis:
    """Analyse a plan before measuring: rank, σ per unknown, unobservable combinations, suggestions.

    The Jacobian is taken at the nominal values (or ``at``, values of unknowns), with ``known``
    values (SI) replacing the model's and the plan's for parameters that are not estimated, as
    in :func:`calibrate`.  ``verdict`` says whether every unknown would be well determined
    (``fit``: the condition-number limit; ``accept_poor_fit``: count a weakly determined plan
    as ``ok``).
    """
    problem = Problem(model, plan, estimate, known=known, priors=priors)
    if problem.params.size == 0:
        raise SolverError("nothing to estimate: name the unknowns (--estimate NAME|GLOB)")
    check_size(1, problem.params.size, problem.n_residuals)
    x = problem.params.from_dict(dict(at or {})) if at else problem.params.x0
    visible = problem.visible(x)
    Jm, Jp = _jacobian_split(problem, x)
    Jm = Jm.copy()
    for rows, seen in zip(problem.measurement_rows, visible):
        if not seen:
            Jm[rows] = 0.0  # a measurement that cannot be made contributes nothing
    obs = analyze(Jm, Jp, problem.params.names, _units(problem), unknown_scales(problem.params), config=observability)
    if suggest and not obs.observable:
        obs.suggestions = rank_candidates(obs, Jm, Jp, _candidate_rows(problem, x, _measured_keys(plan)))
    pts = _point_uncertainties(problem, x, obs.covariance, points, camera)
    invisible = [m.id for m, v in zip(plan.measurements, visible) if not v]
    verdict = assess_plan(problem, obs, config=fit, observability=observability, accept=accept_poor_fit)
    return PlanAnalysis(problem, x, obs, pts, invisible, verdict)
