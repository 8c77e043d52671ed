"""param(p, x): unknown selection by name and glob, known values, configurations."""

from __future__ import annotations

import numpy as np
import pytest

from mbcal.errors import ParameterError
from mbcal.language import load_model, load_model_text
from mbcal.params import ParameterSet

from conftest import MODELS


def test_glob_selects_unknowns_in_model_order():
    model = load_model(MODELS / "teleexistence.mdl")
    ps = ParameterSet(model, ["room.*"])
    assert ps.names == ["room.x", "room.y", "room.z", "room.roll", "room.pitch", "room.yaw"]
    np.testing.assert_array_equal(ps.lower[:3], [-0.1, -0.1, -0.1])


def test_param_maps_x_into_every_configuration_and_back():
    model = load_model(MODELS / "arm7.mdl")
    readings = {"a": {"arm.q1": 0.1}, "b": {"arm.q1": 0.2}}
    ps = ParameterSet(model, ["arm.offset1", "arm.offset4"], configurations=["a", "b"], per_configuration=readings)
    X = np.asarray(ps.param(np.array([0.01, 0.02])))
    i1, i4, q1 = (model.param_index(n) for n in ("arm.offset1", "arm.offset4", "arm.q1"))
    assert X.shape == (2, len(model.params))
    np.testing.assert_array_equal(X[:, i1], [0.01, 0.01])
    np.testing.assert_array_equal(X[:, i4], [0.02, 0.02])
    np.testing.assert_array_equal(X[:, q1], [0.1, 0.2])
    assert ps.to_dict([0.01, 0.02]) == {"arm.offset1": 0.01, "arm.offset4": 0.02}
    np.testing.assert_array_equal(ps.from_dict({"arm.offset4": 0.5}), [0.0, 0.5])


def test_the_callers_values_override_a_files_per_configuration_values():
    """Precedence: the model's nominal < a file's value for every configuration < the file's value
    for one configuration < the caller's (the command line's --set), globally or @config."""
    model = load_model(MODELS / "arm7.mdl")
    q1, q2 = model.param_index("arm.q1"), model.param_index("arm.q2")
    readings = {"a": {"arm.q1": 0.1}, "b": {"arm.q1": 0.2}}
    ps = ParameterSet(model, [], known={"arm.q1": 0.7, "arm.q2": 0.3}, configurations=["a", "b", "c"],
                      per_configuration=readings, overrides={"arm.q1@b": -0.5})  # fmt: skip
    np.testing.assert_array_equal(ps.known[:, q1], [0.1, -0.5, 0.7])
    np.testing.assert_array_equal(ps.known[:, q2], [0.3, 0.3, 0.3])
    ps = ParameterSet(model, [], configurations=["a", "b"], per_configuration=readings, overrides={"arm.q1": 0.9})
    np.testing.assert_array_equal(ps.known[:, q1], [0.9, 0.9])


def test_per_configuration_unknowns_get_one_copy_per_configuration():
    model = load_model_text("param target.x = 0 m per configuration\nparam f = 500\n")
    ps = ParameterSet(model, ["target.x", "f"], configurations=["v1", "v2", "v3"])
    assert ps.names == ["f", "target.x@v1", "target.x@v2", "target.x@v3"]
    X = np.asarray(ps.param(np.array([600.0, 1.0, 2.0, 3.0])))
    np.testing.assert_array_equal(X[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_array_equal(X[:, 1], [600.0] * 3)
    only = ParameterSet(model, ["target.x@v2"], configurations=["v1", "v2", "v3"])
    assert only.names == ["target.x@v2"]


def test_known_values_override_nominal_globally_or_per_configuration():
    model = load_model_text("param a = 1 m\nparam q = 0 deg per configuration\n")
    ps = ParameterSet(model, [], known={"a": 2.0, "q@c2": 0.3}, configurations=["c1", "c2"])
    np.testing.assert_array_equal(ps.known, [[2.0, 0.0], [2.0, 0.3]])


def test_unknown_name_lists_close_matches():
    model = load_model(MODELS / "teleexistence.mdl")
    with pytest.raises(ParameterError, match="no parameter matches 'room.yow'") as info:
        ParameterSet(model, ["room.yow"])
    assert "room.yaw" in str(info.value)


def test_per_configuration_value_for_a_global_parameter_is_refused():
    model = load_model_text("param a = 1 m\n")
    with pytest.raises(ParameterError, match="not declared 'per configuration'"):
        ParameterSet(model, [], configurations=["c"], per_configuration={"c": {"a": 2.0}})


def test_non_finite_known_value_is_refused():
    model = load_model_text("param a = 1 m\n")
    with pytest.raises(ParameterError, match="finite"):
        ParameterSet(model, [], known={"a": float("nan")})


def test_unknown_configuration_is_refused():
    model = load_model_text("param q = 0 per configuration\n")
    with pytest.raises(ParameterError, match="no configuration named 'c3'"):
        ParameterSet(model, ["q@c3"], configurations=["c1", "c2"])
