"""The low-level Marquardt solver: any residual function, batches of restarts, statuses."""

from __future__ import annotations

import numpy as np
import pytest

from mbcal._jax import jnp
from mbcal.errors import SolverError
from mbcal.solver import SolverConfig, Status, least_squares, random_starts


def rosenbrock(x):
    return jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def test_rosenbrock_converges_from_the_classic_start():
    result = least_squares(rosenbrock, np.array([-1.2, 1.0]))
    np.testing.assert_allclose(result.x_best, [1.0, 1.0], atol=1e-10)
    assert result.status_best.converged
    assert result.cost_best < 1e-20


def test_linear_least_squares_matches_the_normal_equations():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(30, 4))
    b = rng.normal(size=30)

    def fun(x, A, b):
        return A @ x - b

    exact = np.linalg.lstsq(A, b, rcond=None)[0]
    tight = SolverConfig(ftol=1e-15, xtol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(
        least_squares(fun, np.zeros(4), args=(A, b), config=tight).x_best, exact, rtol=1e-10, atol=1e-12
    )
    # The default tolerances stop far below any statistical uncertainty, not at round-off.
    np.testing.assert_allclose(least_squares(fun, np.zeros(4), args=(A, b)).x_best, exact, rtol=1e-6, atol=1e-8)


def linear(x, A, b):
    return A @ x - b


def test_tight_tolerances_reach_working_precision_not_a_lucky_rounding():
    # Near the minimum the change of S is below what float64 resolves in S; the old rule (take a
    # step only when the computed change is > 0) stopped 4 of these 20 fits up to 6e-11 from the
    # solution, by the sign of a rounding error.  Steps within the resolution are now taken and
    # reported as converged (issue 16).
    tight = SolverConfig(ftol=1e-15, xtol=1e-15, gtol=1e-15)
    for seed in range(20):
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(40, 5)) * np.array([1.0, 10.0, 100.0, 0.1, 1.0])
        b = 3.0 * rng.normal(size=40)
        exact = np.linalg.lstsq(A, b, rcond=None)[0]
        got = least_squares(linear, np.zeros(5), args=(A, b), config=tight)
        assert got.converged[0], (seed, got.statuses())
        assert np.linalg.norm(got.x_best - exact) <= 1e-12 * np.linalg.norm(exact), seed


def nan_outside(x):
    # Defined only for x[0] > 0: restarts that start elsewhere fail without stopping the others.
    r = jnp.stack([jnp.log(x[0]) - 1.0, x[1] - 2.0])
    return jnp.where(x[0] > 0, r, jnp.nan)


def test_a_failing_restart_gets_its_status_and_does_not_spoil_the_batch():
    starts = np.array([[1.0, 0.0], [-1.0, 0.0], [5.0, 3.0]])
    result = least_squares(nan_outside, starts)
    statuses = result.statuses()
    assert statuses[1] is Status.NON_FINITE
    assert np.isinf(result.cost[1])
    assert statuses[0].converged and statuses[2].converged
    np.testing.assert_allclose(result.x_best, [np.e, 2.0], rtol=1e-10)
    assert result.best in (0, 2)


def test_iteration_limit_is_reported():
    result = least_squares(rosenbrock, np.array([-1.2, 1.0]), config=SolverConfig(max_iterations=3))
    assert result.status_best is Status.MAX_ITERATIONS
    assert result.iterations[0] == 3


def test_every_status_has_a_message():
    for status in Status:
        assert status.message and status.label == status.name.lower()


def test_random_starts_are_reproducible_and_inside_the_range():
    lo = np.array([-1.0, np.nan, 0.0])
    hi = np.array([1.0, np.nan, 10.0])
    a = random_starts(np.array([0.5, 7.0, 3.0]), lo, hi, 50, seed=3)
    b = random_starts(np.array([0.5, 7.0, 3.0]), lo, hi, 50, seed=3)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a[0], [0.5, 7.0, 3.0])
    assert np.all(a[1:, 1] == 7.0)  # no range: stays at its initial value
    assert np.all((a[1:, 0] >= -1) & (a[1:, 0] <= 1)) and np.all((a[1:, 2] >= 0) & (a[1:, 2] <= 10))
    assert len(np.unique(a[1:, 0])) == 49


def line_with_outliers(x, t, y):
    return (x[0] + x[1] * t - y) / 0.1  # whitened: the noise has σ = 0.1


@pytest.mark.parametrize("loss, scale", [("huber", 1.345), ("cauchy", 2.385)])
def test_robust_loss_resists_gross_outliers(loss, scale):
    t = np.linspace(0, 10, 40)
    y = 2.0 + 0.5 * t + np.random.default_rng(1).normal(0, 0.1, t.size)
    y[::5] += 25.0  # 20 % gross errors
    plain = least_squares(line_with_outliers, np.zeros(2), args=(t, y))
    config = SolverConfig(loss=loss, loss_scale=scale)
    robust = least_squares(line_with_outliers, np.zeros(2), args=(t, y), config=config)
    assert np.linalg.norm(robust.x_best - [2.0, 0.5]) < 0.1
    assert np.linalg.norm(plain.x_best - [2.0, 0.5]) > 1.0


def test_bad_config_is_a_clear_error():
    with pytest.raises(SolverError, match="unknown loss 'l1'"):
        SolverConfig(loss="l1")
    with pytest.raises(SolverError, match="loss_scale"):
        SolverConfig(loss_scale=0)


def test_same_inputs_give_bit_identical_results():
    starts = random_starts(np.array([-1.2, 1.0]), np.array([-2.0, -2.0]), np.array([2.0, 2.0]), 8, seed=5)
    a = least_squares(rosenbrock, starts)
    b = least_squares(rosenbrock, starts)
    assert a.x.tobytes() == b.x.tobytes() and a.cost.tobytes() == b.cost.tobytes()


def test_restart_loop_is_vmap_of_a_while_loop_bit_for_bit():
    # Each restart runs until its own test fails; finished restarts are frozen (issue 16).
    from mbcal._jax import jax
    from mbcal.solver import restart_loop

    def cond(s):
        return s[1] < s[2]

    def body(s):
        return (jnp.sin(s[0]) * 1.5 + 0.1, s[1] + 1, s[2])

    state = (jnp.linspace(-2.0, 3.0, 7), jnp.zeros(7, dtype=jnp.int32), jnp.arange(7, dtype=jnp.int32) * 3)
    ours = jax.jit(lambda s: restart_loop(cond, body, s))(state)
    plain = jax.jit(jax.vmap(lambda s: jax.lax.while_loop(cond, body, s)))(state)
    assert [np.asarray(a).tobytes() for a in ours] == [np.asarray(b).tobytes() for b in plain]
    assert np.asarray(ours[1]).tolist() == list(range(0, 21, 3))


def test_mbcal_programs_take_xla_options_only_for_themselves(monkeypatch):
    # mbcal's programs get its XLA options (compile time, issue 16) unless the user's XLA_FLAGS
    # names the option or MBCAL_XLA_OPTIONS=off; nested in a user's transformation they are plain.
    import os

    from jax import export

    from mbcal._jax import compiler_options, jax, jit

    try:
        # Two usable cores: XLA's kernels go to LLVM as two modules (its own split is 32).
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
        ours = {
            "xla_cpu_use_fusion_emitters": False,
            "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
            "xla_disable_hlo_passes": "tree_reduction_rewriter",
            "xla_cpu_parallel_codegen_split_count": 2,
        }
        for env, expected in [
            ({}, ours),
            (
                {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true"},
                {k: v for k, v in ours.items() if "emitters" not in k},
            ),
            (
                {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true --xla_cpu_experimental_ynn_fusion_type="},
                {"xla_disable_hlo_passes": "tree_reduction_rewriter", "xla_cpu_parallel_codegen_split_count": 2},
            ),
            ({"XLA_FLAGS": "--xla_disable_hlo_passes=cse"}, {k: v for k, v in ours.items() if "passes" not in k}),
            ({"MBCAL_XLA_OPTIONS": "off"}, {}),
        ]:
            monkeypatch.delenv("XLA_FLAGS", raising=False)
            monkeypatch.delenv("MBCAL_XLA_OPTIONS", raising=False)
            for k, v in env.items():
                monkeypatch.setenv(k, v)
            compiler_options.cache_clear()
            assert compiler_options() == (expected if jax.default_backend() == "cpu" else {})
        # An XLA that does not know an option refuses the compile: YNNPACK's only from jaxlib 0.10.
        import jaxlib

        monkeypatch.delenv("XLA_FLAGS", raising=False)
        monkeypatch.delenv("MBCAL_XLA_OPTIONS", raising=False)
        monkeypatch.setattr(jaxlib, "__version__", "0.9.1")
        compiler_options.cache_clear()
        older = {k: v for k, v in ours.items() if "ynn" not in k and "split" not in k}
        assert compiler_options() == (older if jax.default_backend() == "cpu" else {})
        # 32 cores or more keep XLA's own split.
        monkeypatch.undo()
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(64)), raising=False)
        monkeypatch.delenv("XLA_FLAGS", raising=False)
        monkeypatch.delenv("MBCAL_XLA_OPTIONS", raising=False)
        compiler_options.cache_clear()
        many = {k: v for k, v in ours.items() if "split" not in k}
        assert compiler_options() == (many if jax.default_backend() == "cpu" else {})
    finally:
        monkeypatch.undo()
        compiler_options.cache_clear()
    f = jit(lambda x: jnp.sin(x) * 2.0)
    x = jnp.linspace(0.0, 1.0, 5)
    want = np.sin(np.linspace(0.0, 1.0, 5)) * 2.0
    np.testing.assert_allclose(f(x), want, rtol=1e-15)
    np.testing.assert_allclose(jax.jit(lambda y: f(y) + 1.0)(x), want + 1.0, rtol=1e-15)
    np.testing.assert_allclose(jax.vmap(f)(x[:, None])[:, 0], want, rtol=1e-15)
    np.testing.assert_allclose(jax.grad(lambda y: f(y).sum())(x), 2.0 * np.cos(np.linspace(0.0, 1.0, 5)), rtol=1e-15)
    np.testing.assert_allclose(export.export(f)(x).call(x), want, rtol=1e-15)
    if jax.default_backend() == "cpu":
        # The options reach XLA: a sum of 1,000 terms compiles without the tree rewrite's
        # reduce-window in mbcal's program, with it in a plain jax.jit of the same function.
        v = jnp.linspace(0.0, 1.0, 1000)
        ours_hlo = jit(lambda y: jnp.sum(y * y)).lower(v).compile().as_text()
        plain_hlo = jax.jit(lambda y: jnp.sum(y * y)).lower(v).compile().as_text()
        assert "reduce-window" in plain_hlo and "reduce-window" not in ours_hlo


def test_a_residual_that_is_not_a_real_vector_is_refused_by_name():
    """A scalar, 2-D, complex or boolean residual failed inside JAX ("tuple index out of range",
    "Cannot concatenate arrays with different numbers of dimensions", "lax.select requires ...")."""
    cases = [
        (lambda b: jnp.sum(b**2), "got shape () of float64"),
        (lambda b: jnp.reshape(b, (1, 2)) - 1.0, "got shape (1, 2) of float64"),
        (lambda b: (b - 1.0) * (1 + 1j), "got shape (2,) of complex128"),
        (lambda b: b > 0, "got shape (2,) of bool"),
    ]
    for fun, said in cases:
        with pytest.raises(SolverError, match="must return a 1-D array of real numbers") as info:
            least_squares(fun, np.array([0.5, 0.2]))
        assert said in str(info.value)
    np.testing.assert_allclose(least_squares(lambda b: b - 1.0, np.array([0.5, 0.2])).x_best, [1.0, 1.0])
