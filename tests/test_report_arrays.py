"""The report's many-row parts as arrays, made when read (issue 16: a warm 13-view calibration as
fast as OpenCV's), the closed-form start's small damping, and the heap given back after large
work (issue 15: memory at 2,000 views)."""

from __future__ import annotations

import subprocess
import sys

import jax
import numpy as np
import pytest

import mbcal
from mbcal.api import _point_uncertainties
from mbcal.errors import MbcalError
from mbcal.measurements.sets import measurements_from_records
from mbcal.modeling import modeler
from mbcal.observability import _largest_across
from mbcal.solver import SolverConfig
from mbcal.workflows.cameras import CLOSED_FORM_LAMBDA, calibrate_cameras, simulate_views

from conftest import MODELS, ROOT

TRUTH = {"cam.fx": 812.0, "cam.fy": 806.5, "cam.cx": 327.0, "cam.cy": 236.0, "cam.k1": -0.21, "cam.k2": 0.08}


@pytest.fixture(scope="module")
def calibrated():
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = simulate_views(model, 9, TRUTH, seed=4, sigma=0.3)[0]
    return model, data, calibrate_cameras(model, data)


def test_the_residual_rows_read_as_a_list_of_the_measurements_at_the_solution(calibrated):
    _model, data, cc = calibrated
    result = cc.result
    rows = result.residuals
    problem = result.problem
    h = problem.predict(result.x)  # the model run again: the rows take h from the residual instead
    assert len(rows) == len(data) == len(list(rows))
    for k in (0, 17, len(rows) - 1, -1):
        row, m = rows[k], data.measurements[k]
        assert (row.id, row.kind, row.config, row.refs) == (m.id, m.kind, m.config, m.refs)
        np.testing.assert_array_equal(row.measured, m.value)
        part = problem.measurement_rows[k % len(rows)]
        np.testing.assert_allclose(row.predicted, h[part], rtol=0, atol=1e-9)
        sigma = np.sqrt(np.diag(m.cov))
        assert row.normalized == pytest.approx(np.linalg.norm((row.predicted - row.measured) / sigma), rel=1e-9)
    assert [r.id for r in rows[3:6]] == [m.id for m in data.measurements[3:6]]
    with pytest.raises(IndexError):
        rows[len(rows)]
    # the arrays behind them, and the worst first as the old sort gave them
    members, measured, predicted = rows.kind("image_point")
    np.testing.assert_array_equal(members, np.arange(len(data)))
    np.testing.assert_allclose(np.sqrt(np.mean(np.sum((measured - predicted) ** 2, axis=1))), cc.rms, rtol=1e-12)
    expected = sorted(rows, key=lambda r: -r.normalized)
    assert [r.id for r in rows.worst(5)] == [r.id for r in expected[:5]]
    assert [r.id for r in result.outliers] == [r.id for r in expected if r.normalized > result.outlier_threshold]


def test_the_predicted_values_from_a_residual_with_correlated_noise_are_the_models():
    """A measurement with a full covariance: h is recovered through its Cholesky factor."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = simulate_views(model, 3, TRUTH, seed=2, sigma=0.3)[0]
    records = []
    for m in data.measurements:
        rec = {"kind": m.kind, "config": m.config, **m.refs, "u": float(m.value[0]), "v": float(m.value[1])}
        rec["cov"] = [[0.09, 0.04], [0.04, 0.16]]
        records.append(rec)
    correlated = measurements_from_records(records, model, configurations=data.configurations)
    result = mbcal.calibrate(model, correlated, ["cam.fx", "cam.fy", "board.*"], restarts=1)
    _members, _measured, predicted = result.residuals.kind("image_point")
    h = result.problem.predict(result.x).reshape(-1, 2)
    np.testing.assert_allclose(predicted, h, rtol=0, atol=1e-9)


def test_point_uncertainties_are_computed_when_read_and_equal_computing_them_at_once(calibrated):
    _model, _data, cc = calibrated
    result = cc.result
    assert result.points._value is None  # nothing computed before the first read
    eager = _point_uncertainties(result.problem, result.x, result.covariance, None, None)
    lazy = result.points
    assert len(lazy) == len(eager) > 0
    assert lazy._value is not None
    # Against first-order propagation written out here: Σ_p = J_p Σ_x J_pᵀ, J_p the Jacobian of the
    # point's world position (modeler(D, param(p, x)) by jax.jacfwd) in its configuration.
    problem = result.problem
    configs = list(problem.params.configurations)
    for k in range(0, len(lazy), 37):
        a = lazy[k]
        c = configs.index(a.configuration)
        J = np.asarray(
            jax.jacfwd(lambda x, c=c, name=a.point: modeler(problem.model, problem.params.param(x)[c]).point(name))(
                result.x
            )
        )
        np.testing.assert_allclose(a.covariance, J @ result.covariance @ J.T, rtol=1e-9, atol=1e-18)
    for a, b in zip(lazy, eager):
        assert (a.point, a.configuration, a.camera) == (b.point, b.configuration, b.camera)
        np.testing.assert_allclose(a.covariance, b.covariance, rtol=1e-12, atol=0)
        assert a.perpendicular == pytest.approx(b.perpendicular, rel=1e-12)
    assert lazy[-1].point == eager[-1].point


def test_a_point_that_does_not_exist_is_an_error_of_the_calibration_not_of_reading_it(calibrated):
    model, data, _cc = calibrated
    with pytest.raises(MbcalError, match="nowhere"):
        mbcal.calibrate(model, data, ["cam.fx"], restarts=1, points=["nowhere"])


@pytest.mark.parametrize("seed", [0, 1])
def test_the_largest_variance_across_a_line_of_sight_in_closed_form(seed):
    """σ⟂² of a point: the largest eigenvalue of its covariance restricted to the plane across the
    line of sight, against the eigenvalues of the projected 3 × 3 matrix."""
    rng = np.random.default_rng(seed)
    k = 500
    u = rng.normal(size=(k, 3))
    u[:3] = np.eye(3)  # along each axis
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    A = rng.normal(size=(k, 3, 3)) * rng.uniform(1e-4, 1.0, size=(k, 1, 3))
    C = A @ np.swapaxes(A, 1, 2)
    C[3] = np.diag([1e-8, 1e-8, 1.0])  # equal across, much larger along: no cancellation
    u[3] = [0.0, 0.0, 1.0]
    P = np.eye(3) - u[:, :, None] * u[:, None, :]
    expected = np.linalg.eigvalsh(P @ C @ P).max(axis=1)
    np.testing.assert_allclose(_largest_across(u, C), expected, rtol=1e-12)


@pytest.mark.slow
def test_zhangs_start_with_a_small_damping_reaches_the_same_minimum_in_fewer_iterations():
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = simulate_views(model, 13, TRUTH, seed=1, sigma=0.3)[0]
    small = calibrate_cameras(model, data).result
    default = calibrate_cameras(model, data, config=SolverConfig()).result  # a config given: used as is
    assert small.run.config.lambda_init == CLOSED_FORM_LAMBDA
    assert default.run.config.lambda_init == SolverConfig().lambda_init
    assert small.solver.status_best.converged and default.solver.status_best.converged
    assert small.solver.iterations[0] < default.solver.iterations[0]
    sigma = np.array([small.std[n] for n in small.names])
    assert np.max(np.abs(small.x - default.x) / sigma) < 1e-3
    assert small.cost <= default.cost * (1 + 1e-9)


RELEASE = """
import resource, sys
import numpy as np
from mbcal._jax import release_memory

def resident():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024

# 100 kB arrays live on malloc's heap; keep every 64th so the freed ones lie between live ones
kept, freed = [], []
for i in range(3000):
    (kept if i % 64 == 63 else freed).append(np.ones(12_500))
before = resident()
del freed
after_free = resident()
release_memory(0)  # below the threshold: nothing
after_small = resident()
release_memory(300 * 2**20)
print(before, after_free, after_small, resident())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_large_work_gives_its_freed_heap_back_to_the_system():
    out = subprocess.run([sys.executable, "-c", RELEASE], capture_output=True, text=True, cwd=ROOT, check=True)
    before, after_free, after_small, after = (float(v) for v in out.stdout.split())
    assert after_free > before - 50  # freed between live arrays: still resident
    assert after_small > before - 50  # too little work to bother
    assert after < after_free - 150  # ~290 MB of 100 kB arrays given back
