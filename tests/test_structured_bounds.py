"""Hard bounds on the Schur-complement solver (issue 15): the dense solver's projected steps taken
by blocks — the same iterates, statuses and active set — and ``calibrate`` keeps the structured
solver for a bounded problem."""

from __future__ import annotations

import numpy as np
import pytest

from mbcal._jax import jnp
from mbcal.errors import SolverError
from mbcal.solver import SolverConfig, Status, least_squares
from mbcal.structured import Structure, least_squares_structured

B, NB, KS, ROWS = 9, 2, 2, 6
T = np.linspace(0.1, 1.6, ROWS)


def _residual(x, y):
    """Block b (u_b, v_b) and the shared (a, c): y_bk ≈ a·exp(−u_b t_k) + c·sin(v_b t_k) + u_b v_b."""
    a, c = x[0], x[1]
    u, v = x[KS::2], x[KS + 1 :: 2]
    model = a * jnp.exp(-u[:, None] * T) + c * jnp.sin(v[:, None] * T) + (u * v)[:, None]
    return (model - y).ravel()


def _problem():
    rng = np.random.default_rng(4)
    truth = np.concatenate([[1.5, 0.8], rng.uniform(0.5, 2.0, 2 * B)])
    y = np.asarray(_residual(truth, np.zeros((B, ROWS)))).reshape(B, ROWS) + rng.normal(0, 0.01, (B, ROWS))
    structure = Structure(
        blocks=KS + np.arange(B * NB).reshape(B, NB),
        shared=np.arange(KS)[None],
        row_block=np.repeat(np.arange(B), ROWS),
        row_group=np.zeros(B * ROWS, dtype=int),
    )
    return truth, y, structure


def _bounds(truth):
    lower = np.full(len(truth), -np.inf)
    upper = np.full(len(truth), np.inf)
    upper[KS + 2 * 3] = truth[KS + 2 * 3] - 0.3  # block 3's u: held below its fit (active)
    lower[0] = truth[0] + 0.2  # the shared a: held above its fit (active)
    lower[KS + 2 * 5 + 1] = 0.0  # block 5's v: a limit far from it (inactive)
    upper[1] = 10.0  # the shared c: likewise
    return lower, upper


@pytest.mark.slow
def test_bounded_structured_iterates_and_active_set_equal_the_dense_solvers():
    truth, y, structure = _problem()
    lower, upper = _bounds(truth)
    rng = np.random.default_rng(5)
    x0 = np.clip(truth + rng.normal(0, 0.15, len(truth)), lower, upper)
    x0 = np.stack([x0, np.clip(truth + rng.normal(0, 0.3, len(truth)), lower - 1, upper + 1)])  # 2nd start: outside
    for cap in (1, 3, 100):  # early iterates, and the converged result
        config = SolverConfig(max_iterations=cap)
        dense = least_squares(_residual, x0, args=(y,), config=config, bounds=(lower, upper))
        ours = least_squares_structured(_residual, x0, structure, args=(y,), config=config, bounds=(lower, upper))
        np.testing.assert_array_equal(ours.x0, dense.x0)  # starts moved inside the same way
        assert np.max(np.abs(ours.x - dense.x)) < 1e-10, cap
        np.testing.assert_array_equal(ours.status, dense.status)
        np.testing.assert_array_equal(ours.iterations, dense.iterations)
        np.testing.assert_allclose(ours.cost, dense.cost, rtol=1e-10)
        assert ours.active is not None and dense.active is not None
        np.testing.assert_array_equal(ours.active, dense.active)
    assert ours.status_best.converged and all(Status(s).converged for s in ours.status)
    expected = np.zeros(len(truth), dtype=int)
    expected[KS + 6], expected[0] = 1, -1  # the two limits set inside the fit are active, the others not
    np.testing.assert_array_equal(ours.active_best, expected)
    assert ours.x_best[KS + 6] == upper[KS + 6] and ours.x_best[0] == lower[0]
    assert np.all(ours.x >= lower) and np.all(ours.x <= upper)
    # Without the active limits the fit moves past them: the bounds, not the data, decided.
    free = least_squares_structured(_residual, x0[0], structure, args=(y,))
    assert free.active is None
    assert free.x_best[KS + 6] > upper[KS + 6] + 0.1 and free.x_best[0] < lower[0] - 0.1


def test_bounds_are_checked_as_the_dense_solver_checks_them_and_infinite_ones_change_nothing():
    truth, y, structure = _problem()
    n = len(truth)
    for lower, upper in ((np.zeros(n), -np.ones(n)), (np.full(n, np.nan), np.ones(n))):
        for solve in (
            lambda b: least_squares(_residual, truth, args=(y,), bounds=b),
            lambda b: least_squares_structured(_residual, truth, structure, args=(y,), bounds=b),
        ):
            with pytest.raises(SolverError, match="bounds must be numbers"):
                solve((lower, upper))
    open_ = least_squares_structured(_residual, truth, structure, args=(y,), bounds=(-np.inf, np.inf))
    plain = least_squares_structured(_residual, truth, structure, args=(y,))
    assert open_.active is None  # all infinite: the unbounded program, bit for bit
    np.testing.assert_array_equal(open_.x, plain.x)


@pytest.fixture(scope="module")
def limited_camera():
    """10 views of the board with hard limits in the model: cam.k1 kept above −0.15 (the truth is
    −0.21: the limit is active) and every view's board.z beyond 5 cm (inactive)."""
    import sys

    import mbcal
    from mbcal.workflows.cameras import default_unknowns, initial_values

    from conftest import MODELS, ROOT

    sys.path.insert(0, str(ROOT / "bench"))
    from scale import synthetic_views

    text = (MODELS / "camera_calibration.mdl").read_text()
    text = text.replace("param cam.k1 = 0 in [-1, 1]", "param cam.k1 = 0 in [-0.15, 1] bounded")
    text = text.replace("param board.z     = 0.5 m  per", "param board.z     = 0.5 m limits [5 cm, inf] per")
    model = mbcal.load_model_text(text, str(MODELS / "limited_camera.mdl"))
    data = synthetic_views(model, 10, seed=6)
    estimate = default_unknowns(model, data)
    start = initial_values(model, data, mbcal.Problem(model, data, estimate).params.names)
    return model, data, estimate, start


@pytest.mark.slow
def test_calibrate_solves_a_bounded_camera_problem_by_blocks_and_reports_what_the_dense_path_does(limited_camera):
    import mbcal
    from mbcal.api import _structure

    model, data, estimate, start = limited_camera
    problem = mbcal.Problem(model, data, estimate)
    assert problem.params.bounds is not None
    chosen = _structure(problem, SolverConfig())  # auto: the bounds no longer send it to the dense solver
    assert chosen is not None and chosen.blocks.shape == (10, 6)
    runs = {
        (structure, analysis): mbcal.calibrate(
            model,
            data,
            estimate,
            restarts=1,
            initial=start,
            points=[],
            analysis=analysis,
            config=SolverConfig(structure=structure),
        )  # fmt: skip
        for structure, analysis in (("structured", "dense"), ("structured", "structured"), ("dense", "dense"))
    }
    ours, blocks, dense = runs.values()
    for result in runs.values():
        assert result.values["cam.k1"] == -0.15  # on the limit, not the truth's −0.21
        assert result.observability.active_bounds == {"cam.k1": "lower"}
        assert all(result.values[f"board.z@view{v:02d}"] > 0.05 for v in range(1, 11))
        assert result.std["cam.k1"] == 0.0 and np.isfinite(result.std["cam.k2"])
    # The structured solve takes the dense solver's path to the same point and active set.
    np.testing.assert_allclose(ours.x, dense.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(ours.solver.active_best, dense.solver.active_best)
    assert ours.cost == pytest.approx(dense.cost, rel=1e-10)
    # The report from the blocks holds cam.k1 as the dense analysis does.
    a, b = ours.observability, blocks.observability
    assert type(b.covariance).__name__ == "BlockCovariance"
    assert a.rank == b.rank == len(a.names) - 1 and a.observable and b.observable
    np.testing.assert_allclose(b.std, a.std, rtol=1e-9)
    assert b.condition == pytest.approx(a.condition, rel=1e-9)
    np.testing.assert_allclose(
        np.asarray(b.covariance), a.covariance, rtol=1e-8, atol=1e-12 * np.abs(a.covariance).max()
    )
    np.testing.assert_array_equal(np.isnan(np.asarray(b.correlation)), np.isnan(a.correlation))
    assert (blocks.verdict.chi2, blocks.verdict.dof) == (pytest.approx(ours.verdict.chi2, rel=1e-9), ours.verdict.dof)
