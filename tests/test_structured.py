"""The Schur-complement solver (issue 15): the same iterates as the dense solver, BAL files, rank
deficient blocks named, the automatic structure of a camera calibration."""

from __future__ import annotations

import json
import sys
from importlib import resources

import jsonschema
import numpy as np
import pytest

import mbcal
from mbcal import structured
from mbcal._jax import jax, jnp
from mbcal.api import _analysed_by_blocks
from mbcal.datasets.bal import BalFileError, bal_residual, read_bal
from mbcal.errors import SolverError
from mbcal.problem import Problem
from mbcal.solver import SolverConfig, least_squares
from mbcal.structured import (
    DENSE_ANALYSIS_ENTRIES,
    Structure,
    analyze_structured,
    bal_structure,
    check_structure,
    compressed_jacobian,
    dense_jacobian,
    least_squares_structured,
    pays,
    square_root_information,
    structure_of,
)
from mbcal.workflows.cameras import default_unknowns, initial_values

from conftest import MODELS, ROOT, run_python, shared_data

sys.path.insert(0, str(ROOT / "bench"))

from scale import synthetic_views  # noqa: E402


@pytest.fixture(scope="module")
def camera20():
    """A 20-view synthetic camera calibration as a model-built problem, from Zhang's start."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 20, seed=1)
    problem = Problem(model, data, default_unknowns(model, data))
    x0 = problem.params.from_dict(initial_values(model, data, problem.params.names))
    return model, data, problem, x0


@pytest.fixture(scope="module")
def camera4():
    """A 4-view camera calibration analysed densely and from its blocks (forced: a few views)."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 4, seed=3)
    estimate = default_unknowns(model, data)
    start = initial_values(model, data, Problem(model, data, estimate).params.names)
    forced = SolverConfig(structure="structured")
    dense, ours = (
        mbcal.calibrate(model, data, estimate, restarts=1, initial=start, analysis=how, suggest=False, config=forced)
        for how in ("dense", "structured")
    )
    assert type(ours.covariance).__name__ == "BlockCovariance"
    return dense, ours


@pytest.fixture(scope="module")
def dubrovnik():
    bal = read_bal(shared_data("bal", "dubrovnik-3-7-pre.txt"))
    C = bal.n_cameras

    def fun(x, ci, pi, obs):
        return bal_residual(x, ci, pi, obs, C)

    return bal, fun, (bal.camera_index, bal.point_index, bal.observed)


@pytest.mark.slow
def test_structured_iterates_agree_with_the_dense_solver_on_a_20_view_calibration(camera20):
    _, _, problem, x0 = camera20
    structure = structure_of(problem)
    assert structure is not None and structure.blocks.shape == (20, 6) and structure.shared.shape == (1, 9)
    assert pays(structure)
    # The blocks are each view's board pose, found by name.
    names = problem.params.names
    assert {names[j] for j in structure.blocks[16]} == {
        f"board.{k}@view17" for k in ("x", "y", "z", "roll", "pitch", "yaw")
    }
    args = (problem.y, problem.params.known)
    for cap in (2, 100):  # the iterate after two iterations, and the converged result
        config = SolverConfig(max_iterations=cap)
        dense = least_squares(problem.residual_function, x0, args=args, config=config, local=problem.local)
        ours = least_squares_structured(
            problem.residual_function, x0, structure, args=args, config=config, local=problem.local
        )
        scale = np.maximum(1.0, np.abs(dense.x_best))
        assert np.max(np.abs(ours.x_best - dense.x_best) / scale) < 1e-10, cap
        assert ours.iterations[0] == dense.iterations[0]
        assert ours.cost_best == pytest.approx(dense.cost_best, rel=1e-10)
    assert ours.status_best.converged
    # σ from the reduced system and the block marginals equal the dense inverse of JᵀJ.
    analysis = analyze_structured(problem.residual_function, ours.x_best, structure, args=args)
    J = problem.jacobian(ours.x_best)
    cov = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(analysis.shared_std, np.sqrt(np.diag(cov))[structure.shared.ravel()], rtol=1e-7)
    np.testing.assert_allclose(analysis.block_std, np.sqrt(np.diag(cov))[structure.blocks], rtol=1e-7)
    block = structure.blocks[4]
    np.testing.assert_allclose(analysis.block_covariance(4), cov[np.ix_(block, block)], rtol=1e-6, atol=1e-18)
    assert analysis.rank == problem.params.size and analysis.observable
    # The full Jacobian assembled from the compressed one is the full Jacobian, and the n × n
    # factor the report analyses has its singular values.
    r, J_assembled, Jc = dense_jacobian(problem.residual_function, ours.x_best, structure, args)
    np.testing.assert_allclose(J_assembled, J, rtol=1e-12, atol=1e-12 * np.abs(J).max())
    R = square_root_information(Jc, structure.row_block, structure)
    assert R.shape == (problem.params.size, problem.params.size)
    sv = np.linalg.svd(J, compute_uv=False)
    np.testing.assert_allclose(np.linalg.svd(R, compute_uv=False), sv, rtol=1e-9, atol=1e-12 * sv[0])


@pytest.mark.parametrize("lapack_blocks", [0, 64])  # unrolled, LAPACK
def test_both_ways_of_inverting_the_blocks_give_the_inverse_and_nan_where_a_block_is_not_positive_definite(
    lapack_blocks, monkeypatch
):
    monkeypatch.setattr(structured, "LAPACK_BLOCKS", lapack_blocks)
    rng = np.random.default_rng(7)
    A = rng.normal(size=(40, 6, 9))
    M = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(6)
    M[5] = -M[5]  # negative definite
    M[9, 2, 2] = -1.0  # indefinite
    # a new function each time: JAX would reuse the first trace (and its way) for the same one
    inverse = np.asarray(jax.jit(lambda m: structured._inverse_blocks(m))(M))
    good = np.setdiff1d(np.arange(40), [5, 9])
    np.testing.assert_allclose(inverse[good], np.linalg.inv(M[good]), rtol=1e-10, atol=1e-12)
    assert np.isnan(inverse[5]).any() and np.isnan(inverse[9]).any()  # the step is then rejected


@pytest.mark.slow
def test_the_unrolled_and_lapack_block_inverses_take_the_same_steps(camera20, monkeypatch):
    """20 views: LAPACK's inverses by default (up to LAPACK_BLOCKS blocks), the unrolled ones
    beyond; both the dense solver's iterates."""
    _, _, problem, x0 = camera20
    structure = structure_of(problem)
    args = (problem.y, problem.params.known)
    config = SolverConfig(max_iterations=3)
    assert structure.n_blocks <= structured.LAPACK_BLOCKS
    dense = least_squares(problem.residual_function, x0, args=args, config=config, local=problem.local)
    solved = []
    for limit in (structured.LAPACK_BLOCKS, 0):
        monkeypatch.setattr(structured, "LAPACK_BLOCKS", limit)
        structured._compiled.cache_clear()  # traced again with this limit
        solved.append(
            least_squares_structured(
                problem.residual_function, x0, structure, args=args, config=config, local=problem.local
            )
        )
    structured._compiled.cache_clear()
    scale = np.maximum(1.0, np.abs(dense.x_best))
    for ours in solved:
        assert np.max(np.abs(ours.x_best - dense.x_best) / scale) < 1e-10
        assert ours.iterations[0] == dense.iterations[0] == 3


@pytest.mark.slow
def test_calibrate_chooses_the_structured_solver_and_reports_what_the_dense_one_does(camera20):
    model, data, problem, _ = camera20
    start = initial_values(model, data, problem.params.names)
    estimate = default_unknowns(model, data)
    auto = mbcal.calibrate(model, data, estimate, restarts=2, initial=start, points=[])
    dense = mbcal.calibrate(model, data, estimate, restarts=2, initial=start, points=[],
                            config=SolverConfig(structure="dense"))  # fmt: skip
    for name in ("cam.fx", "cam.k1", "board.yaw@view07"):
        assert auto.values[name] == pytest.approx(dense.values[name], rel=1e-9, abs=1e-12)
        assert auto.std[name] == pytest.approx(dense.std[name], rel=1e-7)
    assert auto.cost == pytest.approx(dense.cost, rel=1e-10)
    # Forced structured on a problem without configurations of their own: a clear error.
    room = mbcal.load_model(MODELS / "teleexistence.mdl")
    plan = mbcal.read_measurements(ROOT / "measurements" / "room_plan.csv", room)
    room_data = mbcal.simulate(room, plan, {}, noise=0)
    with pytest.raises(SolverError, match="no configurations with unknowns of their own"):
        mbcal.calibrate(room, room_data, ["room.*"], restarts=1, config=SolverConfig(structure="structured"))


@pytest.mark.slow
def test_a_block_seen_along_one_line_is_named_not_crashed():
    """View 3 sees one row of the board only (collinear corners): its rotation about that row is
    unobservable. The structured solve finishes and the analysis names that view's pose."""
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 10, seed=2)
    keep = np.array([m.config != "view03" or m.refs["point"].startswith("board.r0c") for m in data])
    problem = Problem(model, data.subset(keep), default_unknowns(model, data))
    start = initial_values(model, data, problem.params.names)  # from every corner: one row has no homography
    data = data.subset(keep)
    structure = structure_of(problem)
    x0 = problem.params.from_dict(start)
    args = (problem.y, problem.params.known)
    solved = least_squares_structured(problem.residual_function, x0, structure, args=args, local=problem.local)
    assert np.all(np.isfinite(solved.x_best)) and np.isfinite(solved.cost_best)
    analysis = analyze_structured(problem.residual_function, solved.x_best, structure, args=args)
    assert not analysis.observable and analysis.rank == problem.params.size - 1
    [direction] = analysis.unobservable
    assert direction["where"] == "block 2"
    assert all(name.endswith("@view03") for name in direction["combination"])
    assert np.isfinite(analysis.shared_std).all()  # the intrinsics stay determined by the other views
    # calibrate's report from the blocks names it too, and stays finite where it should.
    result = mbcal.calibrate(
        model, data, default_unknowns(model, data), restarts=1, initial=start, analysis="structured", suggest=False
    )
    obs = result.observability
    assert obs.rank == problem.params.size - 1 and [c.names for c in obs.unobservable] == [["board.roll@view03"]]
    assert result.std["board.roll@view03"] == np.inf and np.isfinite(result.std["board.yaw@view03"])
    assert np.isfinite(result.std["cam.fx"]) and np.isfinite(result.verdict.condition)
    view03 = [p for p in result.points if p.configuration == "view03"]
    assert len(view03) == 9 and all(np.isfinite(p.total) for p in view03)  # on the roll axis: not moved by it


@pytest.mark.slow
def test_dubrovnik_converges_to_the_cost_scipy_reaches(dubrovnik):
    import scipy.optimize as scipy_optimize

    bal, fun, args = dubrovnik
    structure = bal_structure(bal)
    check_structure(fun, bal.x0, structure, args)  # every row depends on its point and camera only
    ours = least_squares_structured(fun, bal.x0, structure, args=args)
    f = jax.jit(fun)
    jac = jax.jit(jax.jacfwd(fun))
    theirs = scipy_optimize.least_squares(
        lambda x: np.asarray(f(x, *args)), bal.x0, jac=lambda x: np.asarray(jac(x, *args)), method="trf",
        xtol=1e-15, ftol=1e-15, gtol=1e-15,
    )  # fmt: skip
    initial = float(np.sum(np.asarray(f(bal.x0, *args)) ** 2))
    assert initial > 5000
    assert ours.status_best.converged
    # 38 residuals, 48 unknowns: both fit the data exactly (Σr² at round-off).
    assert ours.cost_best < 1e-12 * initial and 2 * theirs.cost < 1e-12 * initial
    # The first iterates agree with the dense solver too.
    config = SolverConfig(max_iterations=3)
    a = least_squares_structured(fun, bal.x0, structure, args=args, config=config)
    b = least_squares(fun, bal.x0, args=args, config=config)
    assert np.max(np.abs(a.x_best - b.x_best) / np.maximum(1.0, np.abs(b.x_best))) < 1e-10


def test_the_compressed_jacobian_matches_finite_differences(dubrovnik):
    bal, fun, args = dubrovnik
    structure = bal_structure(bal)
    x = bal.x0
    r, Jc = compressed_jacobian(fun, x, structure, args)
    f = jax.jit(fun)
    J = np.zeros((structure.m, structure.n))
    for j in range(structure.n):  # central differences, one unknown at a time
        h = 1e-6 * max(1.0, abs(x[j]))
        e = np.zeros_like(x)
        e[j] = h
        J[:, j] = (np.asarray(f(x + e, *args)) - np.asarray(f(x - e, *args))) / (2 * h)
    rows = np.arange(structure.m)[:, None]
    np.testing.assert_allclose(r, np.asarray(f(x, *args)))
    scale = np.max(np.abs(J))
    np.testing.assert_allclose(Jc[:, :3], J[rows, structure.blocks[structure.row_block]], atol=1e-6 * scale)
    np.testing.assert_allclose(Jc[:, 3:], J[rows, structure.shared[structure.row_group]], atol=1e-6 * scale)


@pytest.mark.slow
def test_a_broken_structure_promise_is_caught():
    def fun(x):
        return jnp.stack([x[0] - 1.0, x[1] + x[2], x[2] * x[0]])  # row 2 mixes block 0 and block 1

    structure = Structure(blocks=[[0], [1]], shared=[[2]], row_block=[0, 1, 1], row_group=[0, 0, 0])
    with pytest.raises(SolverError, match="residual row 2 depends on unknown 0"):
        check_structure(fun, np.ones(3), structure)
    with pytest.raises(SolverError, match="exactly one block"):
        Structure(blocks=[[0], [1]], shared=[[1]], row_block=[0], row_group=[0])


def test_bal_files_with_mistakes_get_located_errors(tmp_path):
    good = "2 1 2\n0 0 1.0 2.0\n1 0 3.0 4.0\n" + "\n".join(["0.1"] * 18) + "\n1\n2\n3\n"
    path = tmp_path / "good.txt"
    path.write_text(good)
    bal = read_bal(path)
    assert bal.cameras.shape == (2, 9) and bal.points.tolist() == [[1.0, 2.0, 3.0]]
    assert bal.observed.tolist() == [[1.0, 2.0], [3.0, 4.0]]
    cases = {
        "2 1 2\n0 0 1.0 2.0\n2 0 3.0 4.0\n": r"bad.txt:3:1: camera 2 is not one of the 2 cameras",
        "2 1 2\n0 0 1.0 zwei\n": r"bad.txt:2:9: expected a number \(y of observation 1\), found 'zwei'",
        "2 1 2\n0 0 1.0 2.0\n": r"bad.txt:2:12: the file ends where the camera of observation 2 was expected",
        good + "7\n": r"bad.txt:\d+:1: unexpected '7' after the last point",
        "2 -1 2\n": r"bad.txt:1:3: the number of points must not be negative",
    }
    for text, message in cases.items():
        bad = tmp_path / "bad.txt"
        bad.write_text(text)
        with pytest.raises(BalFileError, match=message):
            read_bal(bad)
    with pytest.raises(BalFileError, match="missing.txt: cannot read"):
        read_bal(tmp_path / "missing.txt")


@pytest.mark.slow
def test_the_scale_bench_runs_tiny(tmp_path):
    shared_data("bal", "dubrovnik-3-7-pre.txt")
    out = tmp_path / "performance.md"
    proc = run_python("bench/scale.py", "--quick", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert "## Many configurations: the Schur complement" in text and "| 13 | 702 |" in text
    assert "dubrovnik-3-7-pre.txt" in text and "mbcal structured" in text


@pytest.mark.slow
def test_the_command_line_forces_the_solver_and_refuses_what_cannot_be_structured(tmp_path, capsys):
    from mbcal.cli import main
    from mbcal.measurements.io import write_measurements

    room = mbcal.load_model(MODELS / "teleexistence.mdl")
    plan = mbcal.read_measurements(ROOT / "measurements" / "room_plan.csv", room)
    data = tmp_path / "room.csv"
    write_measurements(mbcal.simulate(room, plan, {}, noise=0), data)
    argv = ["solve", str(MODELS / "teleexistence.mdl"), str(data), "--estimate", "room.*", "--restarts", "1"]
    assert main([*argv, "--structure", "structured"]) == 2
    assert "the structured solver cannot solve this problem" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*argv, "--structure", "sparse"])
    assert "invalid choice: 'sparse'" in capsys.readouterr().err


@pytest.mark.slow
def test_the_report_from_the_blocks_equals_the_dense_report(camera20):
    """calibrate's analysis of a structured solve from its blocks (used beyond
    DENSE_ANALYSIS_ENTRIES, forced here with analysis="structured") gives the dense report:
    σ, covariance, correlations, condition, the fit verdict with its suspect (an outlier planted
    in one corner), the weak direction and every point's uncertainty, to 1e-9."""
    model, data, problem, _ = camera20
    start = initial_values(model, data, problem.params.names)
    values = [m.value.copy() for m in data]
    values[37] = values[37] + np.array([5.0, -4.0])  # image_point38: 6σ off
    bad = data.with_values(values)
    estimate = default_unknowns(model, data)
    dense, ours = (
        mbcal.calibrate(model, bad, estimate, restarts=1, initial=start, analysis=how)
        for how in ("dense", "structured")
    )
    a, b = dense.observability, ours.observability
    assert type(b.covariance).__name__ == "BlockCovariance"  # never formed: entries on request
    assert a.rank == b.rank == problem.params.size and a.rank_with_priors == b.rank_with_priors
    assert b.condition == pytest.approx(a.condition, rel=1e-9)
    np.testing.assert_allclose(b.singular_values, a.singular_values[[0, -1]], rtol=1e-9)
    np.testing.assert_allclose(b.std, a.std, rtol=1e-9)
    scale = np.sqrt(np.outer(a.std, a.std))
    assert np.max(np.abs(np.asarray(b.covariance) - a.covariance) / scale) < 1e-9
    assert np.nanmax(np.abs(np.asarray(b.correlation) - a.correlation)) < 1e-9
    i = [problem.params.names.index(n) for n in ("cam.fx", "board.z@view04", "cam.k3")]
    np.testing.assert_allclose(b.covariance[np.ix_(i, i)], a.covariance[np.ix_(i, i)], rtol=1e-9)
    u, v = dense.verdict, ours.verdict
    assert not u.consistent and not v.consistent
    assert (v.chi2, v.dof) == (pytest.approx(u.chi2, rel=1e-9), u.dof)
    assert v.p_value == pytest.approx(u.p_value, rel=1e-9)
    assert (
        [(s.kind, s.ids) for s in v.suspects]
        == [(s.kind, s.ids) for s in u.suspects]
        == [("outliers", ("image_point38",))]
    )
    assert v.suspects[0].excess == pytest.approx(u.suspects[0].excess, rel=1e-9)
    # The dense verdict takes the condition from eigvalsh of the covariance (its smallest eigenvalue,
    # 1e-10 of the largest, only to ~1e-6); the blocks take it from λmax of JᵀJ, to round-off.
    assert v.condition == pytest.approx(u.condition, rel=1e-6)
    assert [w.names for w in v.weak] == [w.names for w in u.weak] == [("cam.k3", "cam.k2")]
    assert v.weak[0].sigma == pytest.approx(u.weak[0].sigma, rel=1e-9)
    assert len(ours.points) == len(dense.points) == 20 * 54
    for p, q in zip(dense.points, ours.points):
        assert (p.point, p.configuration) == (q.point, q.configuration)
        np.testing.assert_allclose(q.covariance, p.covariance, rtol=1e-9, atol=1e-9 * np.abs(p.covariance).max())
        assert q.parallel == pytest.approx(p.parallel, rel=1e-9)
    assert ours.summary().splitlines()[:-1] == dense.summary().splitlines()[:-1]  # all but the time taken
    # The rule of analysis="auto": densely up to DENSE_ANALYSIS_ENTRIES Jacobian entries, from the
    # blocks beyond (300 views of the 9 × 6 board: 32,400 rows × 1,809 unknowns); a bad name is an error.
    views300 = Structure(
        blocks=9 + np.arange(1800).reshape(300, 6), shared=np.arange(9)[None], row_block=np.repeat(np.arange(300), 108),
        row_group=np.zeros(32400, dtype=int),
    )  # fmt: skip
    assert views300.m * views300.n > DENSE_ANALYSIS_ENTRIES > structure_of(problem).m * problem.params.size
    assert _analysed_by_blocks(views300, "auto") and not _analysed_by_blocks(structure_of(problem), "auto")
    assert not _analysed_by_blocks(views300, "dense") and _analysed_by_blocks(structure_of(problem), "structured")
    with pytest.raises(SolverError, match="analysis must be 'auto', 'dense' or 'structured'"):
        mbcal.calibrate(model, bad, estimate, restarts=1, initial=start, analysis="sparse")


@pytest.mark.slow
def test_weak_directions_by_blocks_find_the_dense_ones(camera20, monkeypatch):
    """Beyond WEAK_EXACT tested unknowns the blocks' verdict looks for weak directions in each
    view's block with the shared unknowns (forced here for 20 views): the same weak direction as
    the dense verdict, with σ within a percent (each block's marginal holds the shared one's)."""
    import mbcal.structured as structured

    model, data, problem, _ = camera20
    start = initial_values(model, data, problem.params.names)
    estimate = default_unknowns(model, data)
    dense = mbcal.calibrate(model, data, estimate, restarts=1, initial=start, analysis="dense")
    monkeypatch.setattr(structured, "WEAK_EXACT", 0)
    ours = mbcal.calibrate(model, data, estimate, restarts=1, initial=start, analysis="structured")
    u, v = dense.verdict, ours.verdict
    assert [w.names[:2] for w in v.weak] == [w.names[:2] for w in u.weak] == [("cam.k3", "cam.k2")]
    assert v.weak[0].sigma == pytest.approx(u.weak[0].sigma, rel=1e-2)
    assert v.well_determined == u.well_determined and v.condition == pytest.approx(u.condition, rel=1e-6)


@pytest.mark.slow
def test_the_verdicts_linear_algebra_from_the_blocks_equals_the_dense_one():
    """StructuredLinear (the fit verdict's refit and deletion statistics without the m × n matrix)
    against fit._Linear on 12 views from Zhang's start: S, rank, and the drop of S when a view
    (losing its 6 pose directions), rows across four views (two whole), or six views are set aside — by
    leverages within the rows and, for large groups, by a second factorisation in the unknowns."""
    from mbcal.fit import _Linear
    from mbcal.structured import StructuredLinear

    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data = synthetic_views(model, 12, seed=3)
    problem = Problem(model, data, default_unknowns(model, data))
    x = problem.params.from_dict(initial_values(model, data, problem.params.names))
    structure = structure_of(problem)
    r, Jc = compressed_jacobian(problem.residual_function, x, structure, (problem.y, problem.params.known))
    rows = np.arange(problem.n_residuals)
    dense, ours = _Linear(r, problem.jacobian(x), rows), StructuredLinear(structure, r, Jc, rows)
    assert ours.S == pytest.approx(dense.S, rel=1e-10) and ours.rank == dense.rank == problem.params.size
    for group, lost in ((np.arange(108), 6), (np.arange(50, 400), 12), (np.arange(700), 36)):
        expected = dense.deletion(group)
        assert expected[1] == len(group) - lost
        for limit in (3000, 0):  # the rows' leverages, then the unknowns' space
            ours._GROUP_ROWS = limit
            drop, dof = ours.deletion(group)
            assert dof == expected[1] and drop == pytest.approx(expected[0], rel=1e-9)
    blocks = [np.arange(s.start, s.stop) for s in problem.measurement_rows[:40]]
    np.testing.assert_allclose(ours.deletions(blocks)[0], dense.deletions(blocks)[0], rtol=1e-9)
    np.testing.assert_array_equal(ours.deletions(blocks)[1], dense.deletions(blocks)[1])
    # the same blocks as (start, size) arrays (what the fit verdict passes), in a shuffled order
    order = np.random.default_rng(0).permutation(40)
    spans = problem.row_blocks.take(order)
    for lin in (dense, ours):
        np.testing.assert_allclose(lin.deletions(spans)[0], lin.deletions(blocks)[0][order], rtol=1e-12)
        np.testing.assert_array_equal(lin.deletions(spans)[1], lin.deletions(blocks)[1][order])
    as_lists = [b.tolist() for b in problem.row_blocks]
    assert [np.arange(s.start, s.stop).tolist() for s in problem.measurement_rows] == as_lists


@pytest.mark.slow
def test_structured_and_dense_agree_on_the_seeds_arm_with_unknown_neck_angles():
    """The seed's arm calibration (bench/experiments.py) with each attitude's three neck angles
    unknown too: a block per attitude (3) beside the 7 joint offsets.  The Schur-complement solver
    takes the dense solver's iterates, stops at the same iteration, and its σ from the reduced
    system equals the dense inverse of JᵀJ.  (The room problem has a single configuration: no
    block structure to compare.)"""
    from experiments import CASES

    case = CASES["arm"]
    model = mbcal.load_model(ROOT / case.model)
    plan = mbcal.read_measurements(ROOT / case.plan, model)
    data = mbcal.simulate(model, plan, case.truth, noise=1.0, seed=1)
    neck = {f"neck.q{k}@{c}": v.pop(f"neck.q{k}") for c, v in data.configurations.items() for k in (1, 2, 3)}
    problem = Problem(model, data, [*case.unknowns, "neck.q1", "neck.q2", "neck.q3"])
    structure = structure_of(problem)
    assert structure is not None and structure.blocks.shape == (10, 3) and structure.shared.shape == (1, 7)
    rng = np.random.default_rng(0)
    x0 = problem.params.from_dict({k: v + rng.normal(0.0, 0.02) for k, v in neck.items()})
    args = (problem.y, problem.params.known)
    for cap in (2, 100):
        config = SolverConfig(max_iterations=cap)
        dense = least_squares(problem.residual_function, x0, args=args, config=config, local=problem.local)
        ours = least_squares_structured(
            problem.residual_function, x0, structure, args=args, config=config, local=problem.local
        )
        assert np.max(np.abs(ours.x_best - dense.x_best)) < 1e-10, cap
        assert ours.iterations[0] == dense.iterations[0]
        assert ours.cost_best == pytest.approx(dense.cost_best, rel=1e-10)
    assert ours.status_best.converged
    analysis = analyze_structured(problem.residual_function, ours.x_best, structure, args=args)
    J = problem.jacobian(ours.x_best)
    std = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    np.testing.assert_allclose(analysis.shared_std, std[structure.shared.ravel()], rtol=1e-7)
    np.testing.assert_allclose(analysis.block_std, std[structure.blocks], rtol=1e-7)
    assert analysis.rank == problem.params.size == 37


def test_a_report_by_blocks_is_valid_against_the_schema(camera4):
    """The covariance by blocks (`form: "blocks"`, docs/report.md) is one of the schema's forms:
    every report of a problem analysed from its blocks (beyond ~250 views, or analysis="structured")
    once failed the schema, which required the n × n matrices."""
    schema = json.loads((resources.files("mbcal") / "schemas" / "report.schema.json").read_text(encoding="utf-8"))
    dense, ours = camera4
    for result in (dense, ours):
        jsonschema.validate(json.loads(json.dumps(result.to_json())), schema)
    report = json.loads(json.dumps(ours.to_json()))
    assert report["covariance"]["form"] == "blocks"
    del report["covariance"]["shared"]  # the block form is checked, not merely allowed
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(report, schema)


def test_scalar_entries_of_the_covariance_by_blocks_are_the_dense_ones(camera4):
    """cov[i, j] (docs/scale.md) of the covariance and the correlation by blocks: once a TypeError
    ('numpy.float64' object does not support item assignment) for every pair."""
    dense, ours = camera4
    C, R = dense.covariance, dense.correlation
    n = len(dense.names)
    shared, block = dense.names.index("cam.fx"), dense.names.index("board.z@view02")
    std = np.sqrt(np.diag(C))
    for i, j in [(0, 0), (shared, block), (block, shared), (block, block + 1), (-1, -1), (n - 1, 0)]:
        c, r = ours.covariance[i, j], ours.correlation[i, j]
        assert isinstance(c, float) and isinstance(r, float)
        assert abs(c - C[i, j]) < 1e-9 * std[i] * std[j], (i, j)
        assert r == pytest.approx(R[i, j], abs=1e-9), (i, j)
    assert ours.covariance[np.int64(block), np.int64(block)] == pytest.approx(C[block, block], rel=1e-9)


def test_the_covariance_by_blocks_indexes_as_numpy_does(camera4):
    """The covariance by blocks gives what the dense ndarray gives for the same index, so code
    keeps its meaning when a problem grows past the by-blocks threshold: two index lists are the
    entries at their pairs (once the outer block), np.ix_ the block; `...` and None are refused."""
    dense, ours = camera4
    C, R = dense.covariance, dense.correlation
    n = len(dense.names)
    std = np.sqrt(np.diag(C))
    mask = np.zeros(n, dtype=bool)
    mask[[1, 7, 20]] = True
    a, b = np.array([0, 5, 20, -1]), np.array([3, 5, 11, 0])
    for key in [
        ([0, 1], [0, 1]),
        (a, b),
        (a[:, None], b[None, :]),
        np.ix_(a, b),
        np.ix_(mask, mask),
        ([[0, 1], [2, 3]], [4, 5]),
        (3, [0, 2, 9]),
        ([0, 2, 9], 3),
        (slice(2, 9, 3), [1, 4]),
        ([1, 4], slice(None, 5)),
        (np.array([[0, 1], [2, 3]]), slice(4, 6)),
        (slice(None), 2),
        (2, slice(None)),
        (mask, [0, 1, 2]),
        (slice(1, 4), slice(None, None, -7)),
        ([],),
        [0, 2],
        4,
        slice(3, 5),
        (),
    ]:
        want = C[key]
        got = ours.covariance[key]
        assert np.shape(got) == np.shape(want), key
        I, J = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        norm = (std[I] * std[J])[key]  # the same entries' σ_i σ_j
        assert np.all(np.abs(got - want) <= 1e-9 * norm), key
        np.testing.assert_allclose(ours.correlation[key], R[key], atol=1e-9, err_msg=str(key))
    refused = [
        ((Ellipsis, 0), r"np\.ix_\(a, b\)"),
        (Ellipsis, r"np\.ix_\(a, b\)"),
        ((0, None), r"np\.ix_\(a, b\)"),
        ((0.5, 1), r"np\.ix_\(a, b\)"),
        ((0, 1, 2), "too many indices"),
        ((np.ones(n - 1, dtype=bool), 0), "boolean index"),
        ((n, 0), "out of range"),
    ]
    for key, message in refused:
        with pytest.raises(IndexError, match=message):
            ours.covariance[key]
