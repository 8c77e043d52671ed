"""The library refuses wrong input with an error that names it, where it used to give a silent
wrong answer or a raw exception from deep inside (a read-only review of the Python API): truth
values of no configuration's copy, bounds spread over every unknown, x of the wrong length, a
scan's σ, measurement values set in Python that are not finite, an empty set."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import mbcal
from mbcal.errors import MbcalError, MeasurementFileError, ParameterError, SolverError
from mbcal.solver import least_squares

from conftest import MEASUREMENTS, MODELS


@pytest.fixture(scope="module")
def room():
    return mbcal.load_model(MODELS / "teleexistence.mdl")


@pytest.fixture(scope="module")
def data(room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    return mbcal.simulate(room, plan, {"room.x": 0.01}, noise=1.0, seed=1)


def test_simulate_refuses_truth_it_would_not_use_and_noise_that_is_no_multiplier(room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    nominal = mbcal.simulate(room, plan, {}, noise=0).measurements[0].value
    moved = mbcal.simulate(room, plan, {"room.x": 0.01}, noise=0).measurements[0].value
    assert not np.allclose(nominal, moved)
    for key in ("room.x@default", "room.x@nope"):  # room.x is not per configuration: was the nominal value
        with pytest.raises(ParameterError, match=f"'{key}' is not an unknown"):
            mbcal.simulate(room, plan, {key: 0.01}, noise=0)
    for noise in (-1.0, float("nan"), float("inf")):  # were: no noise, no noise, infinite values
        with pytest.raises(SolverError, match="noise must be a finite number ≥ 0"):
            mbcal.simulate(room, plan, {}, noise=noise)
    with pytest.raises(SolverError, match="seed must be a whole number ≥ 0"):
        mbcal.simulate(room, plan, {}, seed=-1)


def test_least_squares_refuses_bounds_of_another_length_and_an_empty_start():
    def line(x, t, y):
        return x[0] + x[1] * t - y

    t = np.linspace(0, 1, 5)
    y = 1 + 2 * t
    with pytest.raises(
        SolverError, match=r"the lower bounds have shape \(1,\); give one number or one per unknown \(2,\)"
    ):
        least_squares(line, [[0.0, 0.0]], args=(t, y), bounds=([0.0], [1e-3]))  # was: both held at 1e-3
    scalar = least_squares(line, [[0.5, 0.5]], args=(t, y), bounds=(0.0, 10.0))  # one number for all: fine
    np.testing.assert_allclose(scalar.x_best, [1.0, 2.0], atol=1e-8)
    with pytest.raises(SolverError, match="x0 must be"):
        least_squares(line, np.zeros((1, 0)), args=(t, y))


def test_a_parameter_vector_of_the_wrong_length_is_refused(room):
    ps = mbcal.ParameterSet(room, ["room.*"])
    for x in (np.array([0.1, 0.2]), np.arange(8.0)):  # were: padded by the gather's clamping, or cut
        with pytest.raises(ParameterError, match=r"one value per unknown \(6\)"):
            ps.param(x)
        with pytest.raises(ParameterError, match=r"one value per unknown \(6\)"):
            ps.X(x)


def test_measurement_values_set_in_python_are_checked_like_a_files(room, data):
    """Were: "every restart failed: the residuals are not finite" naming nothing, or a raw ValueError."""
    values = [m.value.copy() for m in data]
    values[3] = np.array([np.nan, 1.0])
    ids = [m.id for m in data.measurements]
    cases = [
        (data.with_values(values), ids[3], "its value is not finite"),
        (
            data.with_values([np.zeros(3)] + [m.value for m in data][1:]),
            ids[0],
            "its value or covariance is not of size 2",
        ),
    ]
    for cov in (np.zeros((2, 2)), -np.eye(2), np.array([[1.0, 2.0], [2.0, 1.0]])):
        changed = [dataclasses.replace(data.measurements[0], cov=cov), *data.measurements[1:]]
        bad = mbcal.MeasurementSet(changed, dict(data.known), data.configurations)
        cases.append((bad, ids[0], "its σ or covariance must be finite and positive"))
    for bad, which, message in cases:
        with pytest.raises(MeasurementFileError, match=f"measurement '{which}': {message}"):
            mbcal.calibrate(room, bad, ["room.*"], restarts=2)


def test_an_empty_set_is_refused_and_one_name_is_one_unknown(room, data):
    with pytest.raises(SolverError, match="the measurement set is empty"):
        mbcal.calibrate(room, data.subset([False] * len(data)), ["room.*"], restarts=2)
    one = mbcal.calibrate(room, data, "room.x", restarts=2)  # was: "no parameter matches 'r'"
    assert one.names == ["room.x"]


def test_scans_and_scan_fits_refuse_what_they_would_misread(room):
    from mbcal.range.fit import FitOptions
    from mbcal.range.scans import Scan

    points = np.array([[0.0, 0.8, 1.1], [0.01, 0.8, 1.1], [0.0, 0.81, 1.1]])
    for sigma in (-1e-3, 0.0, float("nan")):
        with pytest.raises(MbcalError, match="sigma must be a positive number of metres"):
            Scan(points, sigma=sigma)
    with pytest.raises(MbcalError, match=r"points must be an \(N, 3\) array, got shape \(3, 2\)"):
        Scan(points[:, :2])
    assert Scan(points.tolist()).points.dtype == np.float64  # a list is taken as an array
    for bad in ({"max_points": 0}, {"restarts": 0}, {"coarse": "sometimes"}, {"voxel": -1.0}, {"loss": "l2"}):
        with pytest.raises(SolverError, match=f"FitOptions.{next(iter(bad))} must be"):
            FitOptions(**bad)


def test_the_model_manager_refuses_settings_it_cannot_use_before_making_its_folder(tmp_path):
    from mbcal.range.manager import ModelManager

    model = MODELS / "room_depth.mdl"
    cases = [
        ({"estimate": []}, "needs unknowns to estimate"),
        ({"estimate": ["room.q"]}, "no param named 'room.q'"),
        ({"estimate": ["room.*"], "drift_k": -1}, "drift_k must be a number of σ > 0"),
        ({"estimate": ["room.*"], "frame": "nope"}, "no frame named 'nope'"),
        ({"estimate": ["room.*"], "sensor": "nope"}, "no range named 'nope'"),
        ({"estimate": ["room.*"], "sigma": 0.0}, "sigma must be a positive number"),
    ]
    for kwargs, message in cases:
        with pytest.raises(MbcalError, match=message):
            ModelManager(model, tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()


def test_a_scan_fits_start_that_names_no_unknown_is_refused(room):
    """fit_scans(initial=...) dropped names that are not unknowns: a typo left the start nominal."""
    from mbcal.range.fit import fit_scans
    from mbcal.range.scans import Scan

    scan = Scan(np.array([[0.0, 0.8, 1.1], [0.01, 0.8, 1.1], [0.0, 0.81, 1.1]]))
    with pytest.raises(ParameterError, match="'zz' is not an unknown"):
        fit_scans(room, [scan], ["room.*"], initial={"zz": 5.0, "room.x": 0.05})


def test_calibrate_options_of_the_wrong_kind_are_named(room, data):
    """Were a NumPy TypeError, an AttributeError naming mbcal's code, or silently accepted
    (a negative outlier threshold listed every measurement)."""
    cases = [
        ({"restarts": 2.5}, "restarts must be a whole number ≥ 1, got 2.5"),
        ({"restarts": "4"}, "restarts must be a whole number ≥ 1, got '4'"),
        ({"config": {"loss": "huber"}}, "config must be a SolverConfig"),
        ({"fit": 0.01}, "fit must be a FitConfig"),
        ({"outlier_threshold": -1.0}, "outlier_threshold must be a finite number of σ ≥ 0"),
        ({"outlier_threshold": float("nan")}, "outlier_threshold must be a finite number of σ ≥ 0"),
        ({"known": [("room.x", 0.0)]}, "known must be a mapping"),
    ]
    for kwargs, message in cases:
        with pytest.raises(SolverError, match=message):
            mbcal.calibrate(room, data, ["room.*"], **kwargs)
    with pytest.raises(SolverError, match="measurements must be a MeasurementSet"):
        mbcal.calibrate(room, list(data), ["room.*"])


def test_values_given_by_name_must_be_finite_numbers(room):
    from mbcal.kinematics import Kinematics
    from mbcal.modeling import modeler

    for value in ("1 cm", float("nan"), None):
        with pytest.raises(ParameterError, match="room.x: a value must be a finite number"):
            modeler(room, {"room.x": value})
    arm = mbcal.load_model(MODELS / "arm7.mdl")
    with pytest.raises(ParameterError, match="arm.offset2: a value must be a finite number"):
        Kinematics(arm, "hand.tip", chain="arm.q*", values={"arm.offset2": float("nan")})
    values = arm.nominal.copy()
    values[arm.param_index("arm.offset2")] = np.inf
    with pytest.raises(ParameterError, match="values: arm.offset2 is not a finite number"):
        Kinematics(arm, "hand.tip", chain="arm.q*", values=values)


def test_solver_settings_kinematics_arguments_and_model_text_are_checked():
    from mbcal.errors import KinematicsError, MdlError
    from mbcal.kinematics import Kinematics
    from mbcal.solver import SolverConfig

    for kwargs in ({"ftol": -1.0}, {"gtol": float("nan")}, {"lambda_init": 0.0}, {"lambda_init": 1e17}):
        with pytest.raises(SolverError, match="must be"):
            SolverConfig(**kwargs)
    arm = mbcal.load_model(MODELS / "arm7.mdl")
    kin = Kinematics(arm, "hand.tip", chain="arm.q*")
    with pytest.raises(KinematicsError, match=rf"one value per chain variable \({kin.n}\), got shape \(6,\)"):
        kin.forward_single(np.zeros(6))  # was an IndexError from the chain's code
    target = np.asarray(kin.position(kin.theta0))
    with pytest.raises(KinematicsError, match="tolerance must be a positive number"):
        kin.ik(target, tolerance=-1.0)  # called a reached target unreached
    with pytest.raises(KinematicsError, match=r"IK orientations must be \(3, 3\) or \(B, 3, 3\)"):
        kin.ik(target, orientation=np.eye(2))
    for text in (None, b"param a = 1 m\n"):
        with pytest.raises(MdlError, match="model text must be a str"):
            mbcal.load_model_text(text)  # type: ignore[arg-type]


def test_numpy_and_jax_scalars_are_numbers_where_numbers_are_checked(room):
    """The checks added above refused np.float32(1) and jnp.array(1.0) for simulate's noise and
    FitOptions' lengths, which worked before them."""
    import jax.numpy as jnp

    from mbcal.range.fit import FitOptions
    from mbcal.range.scans import Scan

    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    reference = mbcal.simulate(room, plan, {}, noise=1.0, seed=2).measurements[0].value
    for noise in (np.float32(1.0), np.int64(1), np.array(1.0), jnp.array(1.0)):
        np.testing.assert_array_equal(
            mbcal.simulate(room, plan, {}, noise=noise, seed=2).measurements[0].value, reference
        )
    FitOptions(voxel=np.float32(0.01), crop=np.float64(0.1), graduated=np.int64(10), misfit_fraction=np.float32(0.2))
    Scan(np.zeros((3, 3)), sigma=np.float32(1e-3))


def test_simulate_noise_multiplies_each_sigma(room):
    """``noise=3`` gives three times the σ (the CLI's ``--noise`` is "in units of each σ"); it
    multiplied the covariance before, which gave √3 of it."""
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    exact = np.array([m.value for m in mbcal.simulate(room, plan, {}, noise=0)])
    one = np.array([m.value for m in mbcal.simulate(room, plan, {}, noise=1.0, seed=4)]) - exact
    three = np.array([m.value for m in mbcal.simulate(room, plan, {}, noise=3.0, seed=4)]) - exact
    np.testing.assert_allclose(three, 3.0 * one, rtol=1e-9, atol=1e-9)
    assert 0.5 < np.std(one) < 2.0  # the plan's σ is 1 px


def test_a_kind_whose_value_is_fixed_refuses_a_value_and_bounds_are_a_pair(tmp_path):
    """A point_to_surface record's 'value' or 'distance' was ignored in silence (S the same for
    0.05, 99 or nothing); bounds=([0, 0],) was an IndexError."""
    from mbcal.measurements.sets import measurements_from_records

    model = mbcal.load_model(MODELS / "room_depth.mdl")
    base = {"kind": "point_to_surface", "object": "room", "x": 0.1, "y": 0.2, "z": 0.3}
    assert len(measurements_from_records([base], model)) == 1
    for extra in ({"value": 0.05}, {"distance": 99.0}):
        with pytest.raises(MeasurementFileError, match="'point_to_surface' takes no value"):
            measurements_from_records([{**base, **extra}], model)
    with pytest.raises(SolverError, match=r"bounds must be \(lower, upper\)"):
        least_squares(lambda x: x, [[1.0, 2.0]], bounds=([0.0, 0.0],))


def test_estimation_runs_in_float64_when_the_caller_turned_x64_off_after_import(room):
    """`jax_enable_x64 = False` after `import mbcal` made least_squares silently run in float32
    (Misra1a ~1e-5 off the certified values) and calibrate stop on a saved float64 program
    ("Dtype mismatch") or solve in float32; the caller's setting is left as it was."""
    import jax
    import jax.numpy as jnp

    def residual(b, x, y):  # Misra1a from the NIST StRD
        return b[0] * (1 - jnp.exp(-b[1] * x)) - y

    x = np.array([77.6, 114.9, 141.1, 190.8, 239.9, 289.0, 332.8, 378.4, 434.8, 477.3, 536.8, 593.1, 689.1, 760.0])
    y = np.array([10.07, 14.73, 17.94, 23.93, 29.61, 35.18, 40.02, 44.82, 50.76, 55.05, 61.01, 66.40, 75.47, 81.78])
    certified = np.array([2.3894212918e02, 5.5015643181e-04])
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    with jax.enable_x64(False):  # in force in this thread, as jax.config.update would be
        fit = least_squares(
            residual, np.array([[500, 1e-4]]), args=(x, y), config=mbcal.SolverConfig(max_iterations=200)
        )
        data = mbcal.simulate(room, plan, {"room.x": 0.02}, noise=0.0, seed=1)
        result = mbcal.calibrate(room, data, ["room.*"], restarts=2)
        analysis = mbcal.observe(room, plan, ["room.*"])
        assert not jax.config.read("jax_enable_x64")  # the caller's setting, unchanged
    assert fit.x_best.dtype == np.float64
    np.testing.assert_allclose(fit.x_best, certified, rtol=1e-8)
    assert abs(result.values["room.x"] - 0.02) < 1e-10 and result.ok
    assert analysis.ok


def test_a_measurement_set_is_indexed_like_the_list_the_docs_call_it(room):
    """docs/api.md: 'a set is a list of Measurement objects', but plan[0] raised TypeError
    ('MeasurementSet' object is not subscriptable)."""
    from mbcal.measurements.sets import MeasurementSet

    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    items = list(plan)
    assert plan[0] is items[0] and plan[-1] is items[-1] and plan[np.int64(2)] is items[2]
    first = plan[:5]
    assert isinstance(first, MeasurementSet) and list(first) == items[:5]
    assert first.known == plan.known and first.configurations == plan.configurations and first.path == plan.path
    assert list(plan[::-1]) == items[::-1] and len(plan[len(plan) :]) == 0
    with pytest.raises(IndexError, match=f"measurement index {len(plan)} is out of range: the set has {len(plan)} "):
        plan[len(plan)]
    for bad in ("lever.tip", True, 1.0):
        with pytest.raises(TypeError, match="indexed by position \\(an int\\) or a slice"):
            plan[bad]
    data = mbcal.simulate(room, plan[:20], {"room.x": 0.01}, noise=0)  # a slice is a set mbcal takes
    assert len(data) == 20
