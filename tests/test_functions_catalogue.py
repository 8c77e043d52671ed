"""The function catalogue: one entry per language function, shared by the checker and both evaluators."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import mbcal
from mbcal import errors
from mbcal.language import functions, ir, soa
from mbcal.language import soa_math as sm
from mbcal.language.functions import CallContext, Parameter, registered_function
from mbcal.language.graph import SCALAR, TRANSFORM, VECTOR, Const, Node, Op
from mbcal.units import LENGTH, describe, unify


@pytest.fixture(autouse=True)
def catalogue_restored():
    """Every test leaves the catalogue as it found it (a leak would change other tests' language)."""
    before = (functions.function_names(), dict(ir.OPS), dict(soa.OPS))
    yield
    assert (functions.function_names(), dict(ir.OPS), dict(soa.OPS)) == before


def double(call: CallContext) -> Node:
    x = call.arg("x", what="the argument of double()")
    return call.op("double", [x], SCALAR, x.dim)


def mean(call: CallContext) -> Node:
    a = call.arg("a", what="the first argument of mean()")
    b = call.arg("b", what="the second argument of mean()")
    ok, dim = unify(a.dim, b.dim)
    if not ok:
        raise errors.UnitError(
            f"mean() needs arguments of one unit, got {describe(a.dim)} and {describe(b.dim)}", call.span
        )
    return call.op("mean", [a, b], SCALAR, dim)


def test_a_registered_function_is_typed_folded_and_evaluated():
    text = "param a = 3 m\nframe f at translate(double(a), 0, 0) {\n  point p = (double(1 m), 0, 0)\n}\n"
    with registered_function("double", ["x"], double, array=lambda xp, x: 2 * x):
        model = mbcal.load_model_text(text)
        assert "double" in functions.function_names()
        pose = model.frames[0].pose
        assert isinstance(pose, Op) and isinstance(pose.args[0].args[0], Op)  # depends on a: kept
        assert isinstance(model.points[0].position, Const)  # double(1 m) is folded while checking
        scene = mbcal.modeler(model, model.nominal)
        np.testing.assert_allclose(scene.point("f.p"), [8.0, 0.0, 0.0])
        np.testing.assert_allclose(mbcal.modeler(model, {"a": 1.5}).point("f.p"), [5.0, 0.0, 0.0])
        # The structure-of-arrays form derived from the array implementation differentiates too.
        jac = jax.jacfwd(lambda X: mbcal.modeler(model, X).point("f.p"))(model.nominal)
        np.testing.assert_allclose(jac, [[2.0], [0.0], [0.0]])
        # Both evaluators agree on the operation.
        node = pose.args[0].args[0]
        assert float(ir.evaluate(node, np.array([4.0]), {}, np)) == 8.0
        assert float(soa.evaluate(node, [4.0], {})) == 8.0
    with pytest.raises(errors.UndefinedNameError, match="unknown function 'double'"):
        mbcal.load_model_text(text)
    assert "double" not in ir.OPS and "double" not in soa.OPS


def test_a_registered_function_checks_units_and_arguments_with_located_errors():
    with registered_function("mean", ["a", "b"], mean, array=lambda xp, a, b: (a + b) / 2):
        model = mbcal.load_model_text("param a = 2 m\npoint p = (mean(a, 4 m), mean(b = 1 m, a = 3 m), 0)\n")
        np.testing.assert_allclose(mbcal.modeler(model, model.nominal).point("p"), [3.0, 2.0, 0.0])
        with pytest.raises(errors.UnitError) as err:
            mbcal.load_model_text("point p = (mean(1 m, 2 deg), 0, 0)\n", "model.mdl")
        assert (
            str(err.value) == "model.mdl:1:12: mean() needs arguments of one unit, got a length (m) and an angle (rad)"
        )
        with pytest.raises(errors.ArgumentError) as err:
            mbcal.load_model_text("point p = (mean(1 m), 0, 0)\n", "model.mdl")
        assert str(err.value) == "model.mdl:1:12: mean() is missing argument 'b'"
        with pytest.raises(errors.UndefinedNameError, match=r"did you mean 'mean'"):
            mbcal.load_model_text("point p = (maen(1 m, 2 m), 0, 0)\n")


def test_a_vector_function_with_an_optional_argument_and_its_own_soa_implementation():
    def scaled(call: CallContext) -> Node:
        v = call.arg("v", kind=VECTOR, size=3, dim=LENGTH, what="scaled() v")
        k = (
            call.arg("k", what="scaled() k")
            if "k" in call.bound
            else Const(kind=SCALAR, dim=None, value=np.asarray(2.0))
        )
        return call.op("scaled", [v, k], VECTOR, v.dim, 3)

    with registered_function(
        "scaled",
        ["v", Parameter("k", required=False)],
        scaled,
        array=lambda xp, v, k: v * k,
        soa=lambda v, k: tuple(sm.mul(c, k) for c in v),
    ):
        model = mbcal.load_model_text(
            "param a = 1 m\npoint p = scaled((a, 0, 1 m))\npoint q = scaled((a, a, a), k = 3)\n"
        )
        scene = mbcal.modeler(model, model.nominal)
        np.testing.assert_allclose(scene.point("p"), [2.0, 0.0, 2.0])
        np.testing.assert_allclose(scene.point("q"), [3.0, 3.0, 3.0])


def test_a_function_built_from_existing_operations_needs_no_implementation():
    def lift(call: CallContext) -> Node:
        h = call.arg("h", dim=LENGTH, what="lift() height")
        zero = Const(kind=SCALAR, dim=None, value=np.asarray(0.0))
        return call.op("translate", [call.op("vec", [zero, zero, h], VECTOR, LENGTH, 3)], TRANSFORM, None)

    with registered_function("lift", ["h"], lift) as entry:
        assert entry.operation is None and "lift" not in ir.OPS
        model = mbcal.load_model_text("param h = 25 cm\nframe f at lift(h) {\n  point p = (1 m, 0, 0)\n}\n")
        np.testing.assert_allclose(mbcal.modeler(model, model.nominal).point("f.p"), [1.0, 0.0, 0.25])


def test_names_that_are_taken_are_refused_and_builtins_stay():
    with pytest.raises(ValueError, match="already"):
        functions.register_function("sqrt", ["a"], double, array=lambda xp, a: a)
    with pytest.raises(ValueError, match="already"):
        functions.register_function("compose", ["a"], double, array=lambda xp, a: a)
    with pytest.raises(ValueError, match="plain name"):
        functions.register_function("two words", ["a"], double)
    with pytest.raises(ValueError, match="built-in"):
        functions.unregister_function("sqrt")
    with pytest.raises(KeyError):
        functions.unregister_function("no_such_function")
    with registered_function("double", ["x"], double, array=lambda xp, x: 2 * x):
        with pytest.raises(ValueError, match="already"):
            functions.register_function("double", ["x"], double, array=lambda xp, x: 2 * x)


def test_the_evaluators_tables_are_the_catalogue():
    names = set(functions.function_names())
    assert {"sqrt", "rot_z", "pose", "look_at", "hypot", "quat"} <= names
    for name in names:
        entry = functions.get_function(name)
        assert entry is not None and entry.builtin
        if entry.operation is not None:
            assert ir.OPS[name] is entry.operation.array and soa.OPS[name] is entry.operation.soa
    internal = set(functions.INTERNAL_OPERATIONS)
    assert {"neg", "add", "sub", "mul", "div", "pow", "vec", "compose"} == internal
    assert not internal & names
    assert set(ir.OPS) == set(soa.OPS) == internal | {n for n in names if functions.get_function(n).operation}
