"""mbcal.staging: the part of a residual computed from its known inputs alone runs in NumPy before
the program; the rest is the program.  Same residual, same Jacobian, the recipe kept in the cache."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from mbcal._jax import jax, jnp
from mbcal.solver import SolverConfig, _compiled, least_squares
from mbcal.staging import Recipe, prepare, split

ROOT = Path(__file__).resolve().parents[1]


def chain(x, readings, y):
    """A two-joint planar chain per configuration: the readings (C, 2) known, x = the offsets and a
    length; the first joint's frame depends on the readings only (the part to move out)."""
    c0, s0 = jnp.cos(readings[:, 0]), jnp.sin(readings[:, 0])
    base = jnp.stack([c0, s0], axis=1) * 0.5  # known only
    twice = jnp.where(readings[:, 1] > 0, readings[:, 1], -readings[:, 1])  # a nested jit (where), known only
    steps = jnp.arange(readings.shape[0]).astype(readings.dtype)  # iota and a convert
    a = readings[:, 0] + readings[:, 1] + x[0]
    tip = base + x[1] * jnp.stack([jnp.cos(a), jnp.sin(a)], axis=1) + 1e-3 * (twice + steps)[:, None]
    return (tip.reshape(-1) - y) / 0.01


@pytest.fixture
def data():
    rng = np.random.default_rng(3)
    readings = rng.uniform(-1.5, 1.5, size=(12, 2))
    truth = np.array([0.05, 0.8])
    y = np.asarray(chain(truth, readings, np.zeros(24))) * 0.01 + rng.normal(0, 0.001, 24)
    return readings, y, truth


def test_the_program_and_recipe_give_the_residual_and_its_jacobian(data):
    readings, y, _ = data
    args = (readings, y)
    made = split(chain, (np.zeros(2),), args)
    assert made.moved > 10 and made.kept > 0, (made.moved, made.kept)
    inputs = made.recipe.inputs(args)
    for x in ([0.0, 1.0], [0.3, 0.7], [-1.0, 2.5]):
        x = np.asarray(x)
        np.testing.assert_allclose(made.program(x, *inputs), chain(x, *args), rtol=1e-14, atol=1e-12)
        J = np.asarray(jax.jacfwd(made.program)(x, *inputs))
        np.testing.assert_allclose(J, jax.jacfwd(chain)(x, *args), rtol=1e-13, atol=1e-10)
        # and against finite differences of the original residual
        h = 1e-6
        fd = np.stack(
            [(np.asarray(chain(x + h * e, *args)) - np.asarray(chain(x - h * e, *args))) / (2 * h) for e in np.eye(2)],
            1,
        )
        np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-5)
    # the inputs of the last arguments are kept; arguments changed in place are seen as new
    assert made.recipe.inputs(args)[0] is made.recipe.inputs(args)[0]
    readings[0, 0] += 0.25
    np.testing.assert_allclose(
        made.program(np.ones(2), *made.recipe.inputs(args)), chain(np.ones(2), *args), rtol=1e-14
    )
    # the program does not compute what was moved: no sine or cosine of the readings alone is left
    traced = jax.make_jaxpr(made.program)(np.zeros(2), *inputs).jaxpr
    assert sum(e.primitive.name in ("sin", "cos") for e in traced.eqns) == 2  # those of x[0] + readings


def test_what_numpy_cannot_compute_here_stays_in_the_program():
    def fun(x, a, k):
        inner = a @ a.T  # a dot product: stays
        halves = k // 2  # integer division: stays
        return x[0] * jnp.sum(inner, axis=1) + halves.astype(x.dtype) + jnp.sin(a[:, 0])  # the sine moves

    a = np.arange(6.0).reshape(3, 2)
    k = np.array([3, -3, 7])
    made = split(fun, (np.ones(1),), (a, k))
    names = [step[0] for step in made.recipe.steps]
    assert "sin" in names and "dot_general" not in names and "div" not in names
    inputs = made.recipe.inputs((a, k))
    np.testing.assert_array_equal(made.program(np.array([2.0]), *inputs), fun(np.array([2.0]), a, k))


def test_a_recipe_reads_back_from_json_bit_for_bit(data):
    readings, y, _ = data

    def fun(x, r, y):
        odd = jnp.where(r[:, 0] > 0, jnp.inf, jnp.nan)  # non-finite literals and results
        return jnp.concatenate([x[0] * jnp.cos(r[:, 0]) - y[:12], jnp.nan_to_num(odd) * 0.0 + x[1]])

    made = split(fun, (np.zeros(2),), (readings, y))
    text = made.recipe.to_json()
    json.loads(text)  # plain JSON text (NaN and inf as text in it)
    again = Recipe.from_json(text)
    assert again.to_json() == text and again.digest == made.recipe.digest  # the exported program's key
    for ours, theirs in zip(made.recipe.inputs((readings, y)), again.inputs((readings, y))):
        np.testing.assert_array_equal(ours, theirs)
    with pytest.raises(ValueError):
        Recipe.from_json(json.dumps({"format": 99}))
    bad = json.loads(text)
    bad["steps"][0][0] = "system"
    with pytest.raises(ValueError, match="unknown operation"):
        Recipe.from_json(json.dumps(bad))


def test_least_squares_staged_gives_the_unstaged_solution(data):
    readings, y, truth = data
    starts = np.array([[0.0, 1.0], [0.2, 0.5], [-0.3, 1.2]])
    staged = least_squares(chain, starts, args=(readings, y), size=24)
    whole = _compiled(chain, SolverConfig(), 24)(starts, (readings, y))
    np.testing.assert_allclose(staged.x, np.asarray(whole[0]), rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(staged.status, np.asarray(whole[2]))
    np.testing.assert_allclose(staged.x_best, truth, atol=5e-3)
    program = prepare(chain, (starts[0],), (readings, y)).program
    assert program is prepare(chain, (starts[0],), (readings * 2, y)).program  # one program per function and shapes


CHILD = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    sys.path.insert(0, {tests!r})
    from test_staging import chain
    from mbcal import staging
    from mbcal.solver import least_squares
    rng = np.random.default_rng(3)
    readings = rng.uniform(-1.5, 1.5, size=(12, 2))
    y = np.asarray(chain(np.array([0.05, 0.8]), readings, np.zeros(24))) * 0.01
    out = least_squares(chain, np.array([[0.0, 1.0], [0.2, 0.5]]), args=(readings, y), size=24, cache_key="chain-test")
    print(json.dumps({{"x": out.x.tolist(), "splits": staging._split_for.cache_info().misses}}))
    """
)


@pytest.mark.slow
def test_a_later_process_reads_the_recipe_and_does_not_trace(tmp_path):
    env = dict(os.environ, MBCAL_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("MBCAL_CACHE", None)
    code = CHILD.format(tests=str(ROOT / "tests"))

    def run():
        proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=ROOT)
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout.strip().splitlines()[-1])

    first, second = run(), run()
    exports = sorted(p.name for p in (tmp_path / "cache" / "exports").iterdir())
    assert any(n.endswith(".recipe.json") for n in exports) and any(n.endswith(".jaxexport") for n in exports)
    assert first["splits"] == 1 and second["splits"] == 0  # the second took the recipe and the program
    assert first["x"] == second["x"]  # bit for bit


def test_a_residual_that_cannot_be_a_cache_key_is_not_split(data):
    readings, y, _ = data

    class Residual:
        __hash__ = None  # type: ignore[assignment]  # an object with __eq__ and no hash

        def __eq__(self, other):
            return isinstance(other, Residual)

        def __call__(self, x, r, y):
            return chain(x, r, y)

    assert prepare(Residual(), (np.zeros(2),), (readings, y)) is None  # not split: no TypeError here


def test_a_residual_whose_trace_fails_is_left_whole_for_the_solver_to_report(data):
    readings, y, _ = data

    def broken(x, r, y):
        return jnp.concatenate([x, r])  # ranks differ: JAX refuses it when traced

    assert prepare(broken, (np.zeros(2),), (readings, y)) is None
    with pytest.raises(TypeError, match="concatenate"):
        least_squares(broken, np.array([[0.0, 1.0]]), args=(readings, y), size=24)


def _whole(fun, x, *args):
    return np.asarray(jax.jit(fun)(x, *args))


def test_from_a_review_scalars_integer_casts_complex_numbers_and_weak_types(tmp_path, monkeypatch):
    """Defects found by a review of the first version: each now gives the unstaged residual."""
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)

    # a scalar argument and a sum over an argument came back as shape (1,)
    def scaled(x, y, s):
        return jnp.stack([x[0] * s, x[1], x[2] * jnp.sum(y)]) - y

    out = least_squares(scaled, np.zeros(3), args=(np.ones(3), 2.0), size=3, cache_key="scalar-test")
    np.testing.assert_allclose(out.x_best, [0.5, 1.0, 1.0 / 3.0], atol=1e-9)

    # float → integer: XLA saturates (NaN → 0); NumPy does not, so it stays in the program
    def cast(x, k):
        return x[0] + jax.lax.convert_element_type(k, jnp.int32).astype(x.dtype)

    k = np.array([np.nan, np.inf, 1e20, 3e9, -1.5])
    made = split(cast, (np.zeros(1),), (k,))
    np.testing.assert_array_equal(made.program(np.zeros(1), *made.recipe.inputs((k,))), _whole(cast, np.zeros(1), k))

    # a complex constant: JSON has no complex numbers; it stays in the program, nothing fails
    def rotated(x, a, y):
        return jnp.abs(a * (1 + 2j)) * x[0] - y

    a, y = np.array([1.0, 2.0, 3.0]), np.array([2.0, 4.0, 6.0])
    out = least_squares(rotated, np.zeros(1), args=(a, y), size=3, cache_key="complex-test")
    np.testing.assert_allclose(out.x_best, [2.0 / np.sqrt(5.0)], rtol=1e-9)

    # a weak-typed JAX scalar keeps float32 arithmetic float32, as unstaged
    def mixed(x, a, w):
        return (a * w).astype(x.dtype) * x[0]

    a32, w = np.array([0.1, 0.2, 0.3], dtype=np.float32), jnp.asarray(0.1)
    prepared = prepare(mixed, (np.ones(1),), (a32, w))
    np.testing.assert_array_equal(prepared.program(np.ones(1), *prepared.inputs), _whole(mixed, np.ones(1), a32, w))


def test_the_kept_inputs_never_alias_a_callers_array():
    def fun(x, d):
        return x[0] * d.reshape(-1) + jnp.sin(d[0, 0])

    data0 = np.arange(6.0).reshape(2, 3) / 10
    made = split(fun, (np.ones(1),), (data0,))
    buf = data0.copy()
    made.recipe.inputs((buf,))
    buf[:] = 5.0  # the caller reuses its buffer
    np.testing.assert_allclose(made.program(np.ones(1), *made.recipe.inputs((data0,))), _whole(fun, np.ones(1), data0))


def test_a_foreign_recipe_file_is_replaced_not_trusted(tmp_path, monkeypatch, data):
    from mbcal import staging

    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    readings, y, truth = data
    key = "0" * 64
    path = staging.recipe_path(key)
    path.parent.mkdir(parents=True)
    for foreign in ("[]", "{", '{"format": 1}', "null"):
        path.write_text(foreign)
        staging._RECIPES.clear()
        prepared = staging.prepare(chain, (np.zeros(2),), (readings, y), key)
        np.testing.assert_allclose(
            prepared.program(truth, *prepared.inputs), _whole(chain, truth, readings, y), rtol=1e-13
        )
        assert Recipe.from_json(path.read_text()).digest == prepared.digest  # written anew
    # a recipe that reads but does not fit (another function's under this key): not used, dropped
    path.write_text(split(lambda x, r: x[0] * jnp.cos(r), (np.zeros(2),), (readings,)).recipe.to_json())
    staging._RECIPES.clear()
    assert staging.prepare(chain, (np.zeros(2),), (readings, y), key) is None and not path.exists()
    assert staging.prepare(chain, (np.zeros(2),), (readings, y), key) is not None and path.exists()


def test_signed_zeros_and_subnormals_as_xla_computes_them():
    """NumPy's sign(−0) is +0 and max(0, −0) −0 where XLA gives −0 and +0, and XLA:CPU flushes
    subnormal numbers: each gave another residual than the program (π for −π, 714 for inf)."""

    def fun(x, a, b):
        return jnp.stack(
            [
                x[0] - jnp.arctan2(jnp.sign(a[0]), -1.0),
                x[0] - 1.0 / jnp.maximum(0.0, a[0]),
                x[0] - jnp.log(b[0] * 0.5),
                x[0] - jnp.log(jnp.abs(b[1])),
            ]
        )

    a, b = np.array([-0.0]), np.array([1e-310, -3e-320])
    made = split(fun, (np.zeros(1),), (a, b))
    np.testing.assert_array_equal(
        made.program(np.zeros(1), *made.recipe.inputs((a, b))), _whole(fun, np.zeros(1), a, b)
    )


def test_weak_and_plain_arguments_of_one_key_do_not_share_a_program(tmp_path, monkeypatch):
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)

    def fun(x, a, b):
        return x - (a * b).astype(x.dtype)  # uint8 arithmetic when a is a weak scalar: 200 * 2 = 144

    b = np.array([2], dtype=np.uint8)
    weak = least_squares(fun, np.zeros(1), args=(jnp.asarray(200), b), size=1, cache_key="weak-key")
    plain = least_squares(fun, np.zeros(1), args=(np.asarray(200), b), size=1, cache_key="weak-key")
    assert weak.x_best[0] == pytest.approx(144.0) and plain.x_best[0] == pytest.approx(400.0)


def test_a_cached_recipe_of_another_split_is_dropped_and_the_problem_solved(tmp_path, monkeypatch, data):
    """A recipe in the cache that this process's split does not give (another JAX made it) must not
    feed its inputs to this process's program: the solve goes on without it."""
    from mbcal import staging

    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    readings, y, truth = data
    starts = np.array([[0.0, 1.0], [0.2, 0.5]])
    first = least_squares(chain, starts, args=(readings, y), size=24, cache_key="stale-test")
    exports = tmp_path / "cache" / "exports"
    (recipe,) = exports.glob("*.recipe.json")
    for program in exports.glob("*.jaxexport"):
        program.unlink()

    def other(x, r, y):  # the same shapes, another split
        return (x[0] * jnp.cos(r[:, 0]) + x[1] * jnp.sin(r[:, 1]) - y[:12]).repeat(2)

    recipe.write_text(split(other, (np.zeros(2),), (readings, y)).recipe.to_json())
    staging._RECIPES.clear()
    again = least_squares(chain, starts, args=(readings, y), size=24, cache_key="stale-test")
    np.testing.assert_allclose(again.x, first.x, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(again.x_best, truth, atol=5e-3)
    assert not recipe.exists()  # dropped: the next run writes its own
