"""Hard limits (issue 14, item 2): the syntax and its located errors, the limits of the unknowns,
projected Marquardt steps that never leave them, and an active bound in the analysis and report."""

from __future__ import annotations

import json
import math
from importlib import resources

import jax
import numpy as np
import pytest

import mbcal
from mbcal.errors import DimensionError, MdlError, MdlSyntaxError, UnitError
from mbcal.params import ParameterSet
from mbcal.solver import SolverConfig, least_squares, random_starts

from conftest import MEASUREMENTS, MODELS, ROOM_TRUTH

jnp = jax.numpy

# ---- the language ----------------------------------------------------------------------------------


def test_bounded_makes_the_search_range_the_limits():
    model = mbcal.load_model_text("param f = 800 in [600, 1000] bounded\nparam g = 1 in [0, 2]")
    f, g = model.param("f"), model.param("g")
    assert (f.lower, f.upper, f.limit_lower, f.limit_upper) == (600, 1000, 600, 1000) and f.limited
    assert (g.limit_lower, g.limit_upper) == (None, None) and not g.limited


def test_limits_have_units_open_ends_and_go_with_every_other_clause():
    model = mbcal.load_model_text(
        "param l = 25 cm limits [0 m, inf]\n"
        "param a = 10 deg in [-5 deg, 15 deg] limits [-90 deg, 90 deg] sigma 2 deg\n"
        "param z = 0.5 m limits [-inf, 2 m] per configuration\n"
        "param k = 0 limits [-1, 1]\n"
    )
    assert (model.param("l").limit_lower, model.param("l").limit_upper) == (0.0, None)
    a = model.param("a")
    assert a.limit_lower == pytest.approx(-math.pi / 2) and a.limit_upper == pytest.approx(math.pi / 2)
    assert a.lower == pytest.approx(math.radians(-5)) and a.sigma == pytest.approx(math.radians(2))
    z = model.param("z")
    assert (z.limit_lower, z.limit_upper, z.per_configuration) == (None, 2.0, True)
    assert (model.param("k").limit_lower, model.param("k").limit_upper) == (-1.0, 1.0)
    assert "limits" in model.summary() and "[0, ∞] m" in model.summary()


def test_a_value_on_its_limit_is_allowed():
    assert mbcal.load_model_text("param k = 0 limits [0, 1]").param("k").limit_lower == 0.0


@pytest.mark.parametrize(
    "text, error, message, column",
    [
        ("param l = 30 cm limits [1 m, 0 m]", DimensionError, "empty limits [1 m, 0 m] for 'l'", 17),
        ("param l = 30 cm limits [1 m, 1 m]", DimensionError, "empty limits", 17),
        (
            "param l = 30 cm limits [1 m, 2 m]",
            DimensionError,
            "the value 30 cm of 'l' lies outside its limits [1 m, 2 m]",
            11,
        ),
        ("param l = 30 cm limits [0 deg, 2 m]", UnitError, "the limits of 'l' are an angle", 25),
        ("param l = 30 cm limits [inf, 2 m]", DimensionError, "the lower limit of 'l' cannot be inf", 25),
        ("param l = 30 cm limits [0, -inf]", DimensionError, "the upper limit of 'l' cannot be -inf", 28),
        (
            "param l = 30 cm in [0, 1 m] limits [10 cm, 2 m]",
            DimensionError,
            "search range [0 m, 1 m] of 'l' reaches",
            21,
        ),
        ("param f = 800 in [600, 1000] bounded limits [0, 1]", MdlError, "both 'bounded' and 'limits", 38),
        ("param f = 8 in [6, 6] bounded", DimensionError, "'f' is bounded by an empty range", 23),
        ("param a = 1 limits [0, b]\nparam b = 2", MdlError, "", 1),
        (
            "param l = 30 cm limits [0, 1 m]\noverride l = 2 m",
            DimensionError,
            "the override 2 m of 'l' lies outside",
            14,
        ),
        # in the units written (the SI numbers alone confused: 1.74533 for 100 deg)
        (
            "param a = 100 deg limits [-60 deg, 60 deg]",
            DimensionError,
            "value 100 deg of 'a' lies outside its limits [-60 deg, 60 deg]",
            11,
        ),
        (
            "param a = 5 mm in [-1 cm, 2 mm] bounded",
            DimensionError,
            "value 5 mm of 'a' lies outside its limits [-1 cm, 2 mm]",
            11,
        ),
        ("param a = 2 limits [-inf, 1]", DimensionError, "value 2 of 'a' lies outside its limits [-inf, 1]", 11),
        (
            "param a = 60.00001 deg limits [-60 deg, 60 deg]",
            DimensionError,
            "value 60.00001 deg of 'a' lies outside its limits [-60 deg, 60 deg]",
            11,
        ),
    ],
)
def test_limit_errors_are_located(text, error, message, column):
    with pytest.raises(error) as info:
        mbcal.load_model_text(text)
    assert message in str(info.value)
    assert info.value.span is not None
    if column > 1:
        assert info.value.span.column == column


@pytest.mark.parametrize("text", ["param l = 30 cm limits [0, 1 m] bounded", "param f = 1 bounded"])
def test_misplaced_keywords_are_syntax_errors(text):
    with pytest.raises(MdlSyntaxError):
        mbcal.load_model_text(text)


@pytest.mark.parametrize("name", ["bounded", "limits"])
def test_the_new_keywords_are_reserved(name):
    with pytest.raises(MdlError, match="reserved"):
        mbcal.load_model_text(f"param {name} = 3")


# ---- the unknowns' limits ---------------------------------------------------------------------------

LIMITED = """
param a = 1 m in [0.5 m, 2 m] bounded
param b = 0 limits [-1, inf]
param c = 3
param q = 0 deg limits [-10 deg, 10 deg] per configuration
"""


def test_parameter_set_gives_the_limits_of_every_unknown_and_copy():
    model = mbcal.load_model_text(LIMITED)
    ps = ParameterSet(model, ["a", "b", "c", "q"], configurations=["one", "two"])
    assert ps.names == ["a", "b", "c", "q@one", "q@two"]
    d = math.radians(10)
    np.testing.assert_allclose(ps.limit_lower, [0.5, -1, -np.inf, -d, -d])
    np.testing.assert_allclose(ps.limit_upper, [2, np.inf, np.inf, d, d])
    assert ps.bounded and ps.bounds is not None
    np.testing.assert_array_equal(ps.bounds[0], ps.limit_lower)
    unlimited = ParameterSet(model, ["c"])
    assert not unlimited.bounded and unlimited.bounds is None


def test_random_starts_are_drawn_inside_the_limits_and_unchanged_without():
    lower, upper = np.array([0.0, -1.0]), np.array([1.0, 1.0])
    plain = random_starts(np.array([0.5, 0.0]), lower, upper, 50, seed=4)
    same = random_starts(np.array([0.5, 0.0]), lower, upper, 50, seed=4, limits=None)
    np.testing.assert_array_equal(plain, same)
    limits = (np.array([0.2, -np.inf]), np.array([0.6, 0.5]))
    held = random_starts(np.array([0.5, 0.0]), lower, upper, 50, seed=4, limits=limits)
    assert np.all(held >= limits[0]) and np.all(held <= limits[1])
    inside = (plain >= limits[0]) & (plain <= limits[1])
    np.testing.assert_array_equal(held[inside], plain[inside])  # the draws themselves are unchanged


# ---- the solver ---------------------------------------------------------------------------------------


def decay(x, t, y):
    return x[0] * jnp.exp(-x[1] * t) + x[2] - y


T = np.linspace(0.0, 4.0, 30)
Y = 2.0 * np.exp(-1.3 * T) + 0.5 + 0.01 * np.sin(7.0 * T)
STARTS = np.array([[1.0, 1.0, 0.0], [3.0, 0.5, 0.1], [0.5, 0.2, 0.3]])


def test_infinite_bounds_run_the_unbounded_program_bit_for_bit():
    free = least_squares(decay, STARTS, args=(T, Y))
    inf = np.full(3, np.inf)
    same = least_squares(decay, STARTS, args=(T, Y), bounds=(-inf, inf))
    for field in ("x", "cost", "status", "iterations"):
        np.testing.assert_array_equal(getattr(free, field), getattr(same, field))
    assert free.active is None and same.active is None
    np.testing.assert_array_equal(free.active_best, [0, 0, 0])


def test_an_inactive_bound_changes_nothing_but_the_program():
    free = least_squares(decay, STARTS, args=(T, Y), config=SolverConfig(ftol=1e-15, xtol=1e-15, gtol=1e-15))
    loose = least_squares(
        decay, STARTS, args=(T, Y), bounds=([0, 0, 0], [10, 10, 10]), config=SolverConfig(ftol=1e-15, xtol=1e-15)
    )
    np.testing.assert_allclose(loose.x_best, free.x_best, rtol=1e-9)
    np.testing.assert_array_equal(loose.active_best, [0, 0, 0])


def test_active_bounds_give_the_constrained_optimum_and_every_iterate_stays_inside():
    import scipy.optimize as scipy_optimize

    seen = []

    def watched(x, t, y):
        jax.debug.callback(lambda v: seen.append(np.array(v)), x)
        return decay(x, t, y)

    lower, upper = np.array([-np.inf, -np.inf, -np.inf]), np.array([np.inf, 1.0, 0.3])
    config = SolverConfig(ftol=1e-15, xtol=1e-15, gtol=1e-15, max_iterations=200)
    fit = least_squares(watched, STARTS[:2], args=(T, Y), bounds=(lower, upper), config=config)
    evaluated = np.concatenate([np.atleast_2d(v) for v in seen])
    assert len(evaluated) > 4
    assert np.all(evaluated <= upper) and np.all(evaluated >= lower)
    reference = scipy_optimize.least_squares(
        lambda b: b[0] * np.exp(-b[1] * T) + b[2] - Y,
        [1.0, 0.9, 0.2],
        bounds=(lower, upper),
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    for k in range(2):
        assert fit.statuses()[k].converged
        np.testing.assert_allclose(fit.x[k], reference.x, rtol=1e-7)
        assert fit.x[k][2] == 0.3  # exactly on the bound
        np.testing.assert_array_equal(fit.active[k], [0, 0, 1])


def test_a_start_outside_the_bounds_is_moved_onto_them():
    fit = least_squares(decay, [[1.0, 5.0, 0.0]], args=(T, Y), bounds=([0, 0, 0], [10, 2, 10]))
    np.testing.assert_array_equal(fit.x0, [[1.0, 2.0, 0.0]])
    assert fit.status_best.converged and np.all(fit.x_best <= [10, 2, 10])


def test_lower_bound_active_and_an_unseen_unknown_on_its_bound_stays_free():
    def fun(x, t, y):
        return x[0] * t + 0.0 * x[1] - y  # x[1] changes nothing

    t = np.linspace(1, 2, 5)
    fit = least_squares(fun, [[1.0, 0.0]], args=(t, -t), bounds=([0.0, 0.0], [5.0, 1.0]))
    np.testing.assert_array_equal(fit.x_best, [0.0, 0.0])
    np.testing.assert_array_equal(fit.active_best, [-1, 0])  # x[1] sits on its bound, nothing pushes it


def test_bad_bounds_are_refused():
    with pytest.raises(mbcal.errors.SolverError, match="lower ≤ upper"):
        least_squares(decay, STARTS, args=(T, Y), bounds=([0, 0, 1], [1, 1, 0]))


# ---- calibration: an active bound in the analysis and the report -----------------------------------------

BOUNDED_X = "param room.x     = 0 m   in [-1 cm, 1 cm] bounded"


@pytest.fixture(scope="module")
def limited_room():
    text = (MODELS / "teleexistence.mdl").read_text(encoding="utf-8")
    assert "param room.x     = 0 m   in [-10 cm, 10 cm]" in text
    text = text.replace("param room.x     = 0 m   in [-10 cm, 10 cm]", BOUNDED_X)
    return mbcal.load_model_text(text, str(MODELS / "teleexistence.mdl"))


@pytest.fixture(scope="module")
def pushed(limited_room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", limited_room)
    return mbcal.simulate(limited_room, plan, ROOM_TRUTH, noise=1.0, seed=11)  # room.x = 2 cm: past 1 cm


@pytest.fixture(scope="module")
def held(limited_room, pushed):
    return mbcal.calibrate(limited_room, pushed, ["room.*"], restarts=8, seed=0)


def test_the_estimate_is_held_at_its_limit_with_sigma_zero(held):
    assert held.converged
    assert held.values["room.x"] == 0.01
    assert held.observability.active_bounds == {"room.x": "upper"}
    np.testing.assert_array_equal(held.solver.active_best, [1, 0, 0, 0, 0, 0])
    assert held.std["room.x"] == 0.0
    assert np.all(held.covariance[0] == 0) and np.all(held.covariance[:, 0] == 0)
    assert np.all(np.isnan(held.correlation[0]))
    assert held.observability.observable and held.observability.rank == 5 and held.observability.n_free == 5
    assert held.dof == held.problem.n_residuals - 5
    assert np.all(held.solver.x0[:, 0] >= -0.01) and np.all(held.solver.x0[:, 0] <= 0.01)  # starts inside


def test_the_others_and_their_covariance_are_those_with_the_bounded_one_held(limited_room, pushed, held):
    others = ["room.y", "room.z", "room.roll", "room.pitch", "room.yaw"]
    fixed = mbcal.calibrate(limited_room, pushed, others, restarts=8, seed=0, known={"room.x": 0.01})
    for name in others:
        assert held.values[name] == pytest.approx(fixed.values[name], abs=1e-7)
        assert held.std[name] == pytest.approx(fixed.std[name], rel=1e-6)
    np.testing.assert_allclose(held.covariance[1:, 1:], fixed.covariance, rtol=1e-5, atol=1e-14)


def test_the_report_names_the_active_bound(held):
    import jsonschema

    report = json.loads(json.dumps(held.to_json()))
    assert report["active_bounds"] == [{"name": "room.x", "bound": "upper", "limit": 0.01, "unit": "m"}]
    assert report["parameters"]["room.x"]["std"] == 0.0
    assert report["covariance"]["correlation"][0][1] is None
    schema = json.loads((resources.files("mbcal") / "schemas" / "report.schema.json").read_text(encoding="utf-8"))
    assert "active_bounds" in schema["oneOf"][0]["properties"]
    jsonschema.validate(report, schema)
    text = held.summary()
    assert "0 (at bound)" in text
    assert "at an active bound (1): room.x at its upper limit 0.01 m" in text
    assert "rank 5 of 5 free (1 held at an active bound)" in text


@pytest.mark.slow
def test_an_unreached_limit_changes_nothing(room, limited_room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    truth = {**ROOM_TRUTH, "room.x": 0.004}
    data = mbcal.simulate(room, plan, truth, noise=1.0, seed=11)
    free = mbcal.calibrate(room, data, ["room.*"], restarts=4, seed=0, suggest=False)
    limited = mbcal.calibrate(limited_room, data, ["room.*"], restarts=4, seed=0, suggest=False)
    assert limited.observability.active_bounds == {} and limited.to_json()["active_bounds"] == []
    for name, value in free.values.items():
        assert limited.values[name] == pytest.approx(value, abs=1e-7)
        assert limited.std[name] == pytest.approx(free.std[name], rel=1e-5)


def test_the_calibrated_model_says_an_unknown_was_held_at_its_limit_not_sigma_0(tmp_path):
    """An unknown the data push past its hard limit ends on it with σ 0: the calibrated model's
    header read '(σ 0)', as if perfectly determined; it names the limit now."""
    path = tmp_path / "held.mdl"
    path.write_text(
        "param a = 0.5 m in [0 m, 1 m] bounded\nparam b = 0 m in [-1 m, 1 m]\npoint p = (a, b, 0)\nmeasure point3d\n"
    )
    model = mbcal.load_model(path)
    plan = mbcal.measurements_from_records([{"kind": "point3d", "point": "p", "sigma": 0.01}], model)
    data = mbcal.simulate(model, plan, {"a": -0.2, "b": 0.3}, noise=0.0, seed=0)
    result = mbcal.calibrate(model, data, ["a", "b"], restarts=2)
    assert result.observability.active_bounds == {"a": "lower"} and result.values["a"] == 0.0
    result.write_model(tmp_path / "out.mdl")
    header = [line for line in (tmp_path / "out.mdl").read_text().splitlines() if line.startswith("#   ")]
    (a,) = [line for line in header if line.startswith("#   a =")]
    (b,) = [line for line in header if line.startswith("#   b =")]
    assert a.endswith("(held at its lower limit)") and "σ" not in a
    assert "(σ " in b
