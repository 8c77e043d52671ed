"""The catalogue of the language's functions, and of the operations of the expression graph.

Every function a model may call — ``sqrt``, ``rot_z``, ``look_at``, ... — is one
:class:`Function` entry here: its signature, its typing rule (how the checker types a call,
checks its units and builds the graph node) and, through its :class:`Operation`, the numeric
implementations both evaluators use: the array one (numpy to fold constants, JAX in
:func:`mbcal.language.ir.evaluate`) and the structure-of-arrays one
(:func:`mbcal.language.soa.evaluate`).  The checker's function table and the evaluators'
operation tables are views of this catalogue, so adding a function is one call to
:func:`register_function` — the built-in functions below are registered exactly that way.

Operations that are not functions of the language — the arithmetic of operators, ``vec`` for
``(x, y, z)`` and ``compose`` for a product of transforms — are :data:`INTERNAL_OPERATIONS`.
The checker also builds the operations of some built-in functions itself — ``translate`` (a
position used as a pose), ``norm`` (axes), ``dot`` (mesh scales) and ``rpy`` (``pose``) — so
built-in functions can be neither replaced nor unregistered.

Example: a function ``double(x) = 2 x`` that keeps the unit of its argument::

    from mbcal.language.functions import registered_function
    from mbcal.language.graph import SCALAR

    def double(call):
        x = call.arg("x", what="the argument of double()")
        return call.op("double", [x], SCALAR, x.dim)

    with registered_function("double", ["x"], double, array=lambda xp, x: 2 * x):
        model = mbcal.load_model_text("param a = 3 m\\npoint p = (double(a), 0, 0)")
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np

from mbcal.errors import ArgumentError, DimensionError, MdlTypeError, SourceSpan, UnitError
from mbcal.geometry import transforms as geo
from mbcal.language import ast
from mbcal.language import soa_math as sm
from mbcal.language.arguments import Parameter
from mbcal.language.graph import SCALAR, TRANSFORM, VECTOR, Const, Node, describe_kind, note_use, product_dim
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH, Dim, describe, fits, unify

__all__ = [
    "ArrayImplementation",
    "SoaImplementation",
    "TypingRule",
    "CallContext",
    "Operation",
    "Function",
    "Parameter",
    "INTERNAL_OPERATIONS",
    "ARRAY_IMPLEMENTATIONS",
    "SOA_IMPLEMENTATIONS",
    "elementwise",
    "get_function",
    "function_names",
    "runtime_functions",
    "operation",
    "register_function",
    "unregister_function",
    "registered_function",
    "look_at_problem",
]

ArrayImplementation = Callable[..., Any]
"""``f(xp, *args)``: an operation on numpy or JAX arrays; ``xp`` is the array module."""

SoaImplementation = Callable[..., Any]
"""``f(*args)``: an operation on structure-of-arrays values (see :mod:`mbcal.language.soa_math`)."""


class CallContext(Protocol):
    """What a typing rule sees of one call: its arguments and the checker's help with them.

    Attributes
    ----------
    name : str
        The function called.
    span : SourceSpan
        The call in the source.
    bound : Mapping[str, ast.Expr]
        The arguments given, by parameter name (optional ones may be absent).
    """

    name: str
    span: SourceSpan
    bound: Mapping[str, ast.Expr]

    def arg(self, key: str, *, kind: str = SCALAR, dim: Dim | None = None, size: int = 0, what: str = "") -> Node:
        """Compile argument ``key``, checking its kind, size and unit (``what`` names it in errors)."""
        ...

    def compile(self, key: str) -> Node:
        """Compile argument ``key`` as it is, of any kind."""
        ...

    def axis(self, key: str) -> Node:
        """Compile argument ``key`` as an axis: ``x``, ``-y``, ... or a non-zero 3-vector, normalised."""
        ...

    def op(self, name: str, args: Sequence[Node], kind: str, dim: Dim | None, size: int = 0) -> Node:
        """The node of operation ``name`` on ``args`` (folded to a constant when they all are)."""
        ...


TypingRule = Callable[[CallContext], Node]
"""``rule(call) -> Node``: types one call, checks its units and builds its node."""


@dataclass(frozen=True)
class Operation:
    """An operation of the expression graph and how each evaluator computes it.

    Attributes
    ----------
    name : str
        The name :class:`~mbcal.language.graph.Op` nodes carry.
    array : ArrayImplementation
        ``f(xp, *args)`` on arrays: folds constants (numpy) and builds the JAX graph.
    soa : SoaImplementation
        ``f(*args)`` on structure-of-arrays values, for the modeler's hot path.
    """

    name: str
    array: ArrayImplementation
    soa: SoaImplementation


@dataclass(frozen=True)
class Function:
    """A function of the language.

    Attributes
    ----------
    name : str
        What model text calls.
    parameters : tuple of Parameter
        The signature, in positional order; keywords use the same names.
    typing : TypingRule
        Types a call and builds its node.
    operation : Operation or None
        The operation of the same name the rule builds; None when the rule combines others
        (``pose`` is a ``translate`` composed with an ``rpy``).
    builtin : bool
        Part of the language (cannot be unregistered).
    """

    name: str
    parameters: tuple[Parameter, ...]
    typing: TypingRule
    operation: Operation | None = None
    builtin: bool = False


def elementwise(array: ArrayImplementation) -> SoaImplementation:
    """The structure-of-arrays form of an array implementation of a function of scalars.

    Constants (Python floats) are computed with numpy, so they stay constants while tracing;
    anything else with ``jax.numpy``.  Right for functions whose arguments and value are
    scalars; vectors and transforms need an implementation of their own.

    Parameters
    ----------
    array : ArrayImplementation
        ``f(xp, *args)``.

    Returns
    -------
    SoaImplementation
        ``f(*args)``.
    """

    def soa(*args: Any) -> Any:
        if all(isinstance(a, float) for a in args):
            return sm.constant(lambda *values: array(np, *values), *args)
        return array(sm.jnp(), *args)

    return soa


# ---- internal operations: what operators and vector literals compile to ---------------------------


def _vec(xp: Any, *items: Any) -> Any:
    return xp.stack([xp.asarray(i, dtype=float) for i in items])


def _neg_soa(a: Any) -> Any:
    return tuple(sm.neg(x) for x in a) if isinstance(a, tuple) else sm.neg(a)


def _pow_soa(a: Any, b: Any) -> Any:
    return (a**b) if not (isinstance(a, float) and isinstance(b, float)) else sm.constant(np.power, a, b)


_INTERNAL: dict[str, Operation] = {
    op.name: op
    for op in (
        Operation("neg", lambda xp, a: -a, _neg_soa),
        Operation("add", lambda xp, a, b: a + b, lambda a, b: sm.broadcast(sm.add, a, b)),
        Operation("sub", lambda xp, a, b: a - b, lambda a, b: sm.broadcast(sm.sub, a, b)),
        Operation("mul", lambda xp, a, b: a * b, lambda a, b: sm.broadcast(sm.mul, a, b)),
        Operation("div", lambda xp, a, b: a / b, lambda a, b: sm.broadcast(sm.div, a, b)),
        Operation("pow", lambda xp, a, b: a**b, _pow_soa),
        Operation("vec", _vec, lambda *items: tuple(items)),
        Operation("compose", lambda xp, a, b: a @ b, sm.compose),
    )
}

INTERNAL_OPERATIONS: Mapping[str, Operation] = MappingProxyType(_INTERNAL)
"""The operations that are not functions of the language, by name."""

# The catalogue.  The implementation tables are kept beside it so that evaluating an
# operation is one dictionary look-up, as it was before the catalogue.
_FUNCTIONS: dict[str, Function] = {}
_OPERATIONS: dict[str, Operation] = dict(_INTERNAL)
_ARRAY: dict[str, ArrayImplementation] = {name: op.array for name, op in _INTERNAL.items()}
_SOA: dict[str, SoaImplementation] = {name: op.soa for name, op in _INTERNAL.items()}

ARRAY_IMPLEMENTATIONS: Mapping[str, ArrayImplementation] = MappingProxyType(_ARRAY)
"""Every operation's array implementation by name (a live view: registrations show)."""

SOA_IMPLEMENTATIONS: Mapping[str, SoaImplementation] = MappingProxyType(_SOA)
"""Every operation's structure-of-arrays implementation by name (a live view)."""


def get_function(name: str) -> Function | None:
    """The function called ``name``, or None."""
    return _FUNCTIONS.get(name)


def function_names() -> tuple[str, ...]:
    """The names of the language's functions, in the order they were registered."""
    return tuple(_FUNCTIONS)


def runtime_functions() -> list[Function]:
    """Functions registered at run time (not part of the language as shipped).  Their code is not
    part of mbcal's source fingerprint, so compiled programs are not cached across processes
    while any is registered (:meth:`mbcal.problem.Problem.fingerprint`)."""
    return [f for f in _FUNCTIONS.values() if not f.builtin]


def operation(name: str) -> Operation:
    """The operation called ``name`` (internal or a function's); KeyError if there is none."""
    return _OPERATIONS[name]


def _parameter(p: str | tuple[str, bool]) -> Parameter:
    return Parameter(p) if isinstance(p, str) else Parameter(*p)


def _register(
    name: str,
    parameters: Sequence[str | tuple[str, bool]],
    typing: TypingRule,
    array: ArrayImplementation | None,
    soa: SoaImplementation | None,
    builtin: bool,
) -> Function:
    if not name.isidentifier():
        raise ValueError(f"a function name is a plain name, got {name!r}")
    if name in _FUNCTIONS or name in _OPERATIONS:
        raise ValueError(f"'{name}' is already a function or an operation")
    params = tuple(_parameter(p) for p in parameters)
    names = [p.name for p in params]
    if len(set(names)) != len(names) or not all(n.isidentifier() for n in names):
        raise ValueError(f"{name}(): parameter names must be distinct plain names, got {names}")
    if array is None and soa is not None:
        raise ValueError(f"{name}(): a structure-of-arrays implementation needs the array one too")
    op = None
    if array is not None:
        op = Operation(name, array, soa if soa is not None else elementwise(array))
        _OPERATIONS[name] = op
        _ARRAY[name] = op.array
        _SOA[name] = op.soa
    function = Function(name, params, typing, op, builtin)
    _FUNCTIONS[name] = function
    return function


def register_function(
    name: str,
    parameters: Sequence[str | tuple[str, bool]],
    typing: TypingRule,
    array: ArrayImplementation | None = None,
    soa: SoaImplementation | None = None,
) -> Function:
    """Add a function to the language.

    Parameters
    ----------
    name : str
        What model text calls; also the name of the operation when ``array`` is given.
    parameters : sequence of str, (name, required) or Parameter
        The signature in positional order; a bare name is required.
    typing : TypingRule
        ``rule(call) -> Node``: compiles the arguments through ``call`` (a
        :class:`CallContext`), checks their kinds and units, and returns ``call.op(name, ...)``
        — or a combination of existing operations.
    array : ArrayImplementation, optional
        ``f(xp, *args)`` for the operation ``name``; leave out when ``typing`` builds only
        existing operations.
    soa : SoaImplementation, optional
        ``f(*args)`` on structure-of-arrays values; by default :func:`elementwise` of ``array``,
        which is right for functions of scalars.

    Returns
    -------
    Function
        The new entry.

    Raises
    ------
    ValueError
        The name is taken (by a function or an internal operation) or not a plain name.
    """
    return _register(name, parameters, typing, array, soa, builtin=False)


def unregister_function(name: str) -> None:
    """Remove a function added with :func:`register_function`, and its operation.

    Raises
    ------
    KeyError
        No such function.
    ValueError
        ``name`` is a built-in function.
    """
    function = _FUNCTIONS[name]
    if function.builtin:
        raise ValueError(f"'{name}' is a built-in function of the language")
    del _FUNCTIONS[name]
    if function.operation is not None:
        del _OPERATIONS[name], _ARRAY[name], _SOA[name]


@contextlib.contextmanager
def registered_function(
    name: str,
    parameters: Sequence[str | tuple[str, bool]],
    typing: TypingRule,
    array: ArrayImplementation | None = None,
    soa: SoaImplementation | None = None,
) -> Iterator[Function]:
    """:func:`register_function` for the duration of a ``with`` block (tests, experiments).

    Models checked inside the block may be evaluated after it only while the function is
    registered again: the graph refers to the operation by name.
    """
    function = register_function(name, parameters, typing, array, soa)
    try:
        yield function
    finally:
        unregister_function(name)


# ---- typing rules of the built-in functions -------------------------------------------------------


def _scalar_rule(arg_dim: Dim | None, result: Dim | None, *, accept: tuple[Dim, ...] = ()) -> TypingRule:
    def rule(call: CallContext) -> Node:
        a = call.arg("a", what=f"the argument of {call.name}()")
        if arg_dim is not None and not (fits(a.dim, arg_dim) or a.dim in accept):
            raise UnitError(f"{call.name}() takes {describe(arg_dim)}, got {describe(a.dim)}", call.bound["a"].span)
        note_use(a, arg_dim)
        return call.op(call.name, [a], SCALAR, result)

    return rule


def _same_unit_rule(result: str = "same") -> TypingRule:
    def rule(call: CallContext) -> Node:
        op = call.name
        a = call.arg("a", what=f"the first argument of {op}()")
        b = call.arg("b", what=f"the second argument of {op}()")
        ok, dim = unify(a.dim, b.dim)
        if not ok:
            raise UnitError(
                f"{op}() needs arguments of one unit, got {describe(a.dim)} and {describe(b.dim)}", call.span
            )
        note_use(a, dim)  # atan2(a, 1 m): a is a length
        note_use(b, dim)
        return call.op(op, [a, b], SCALAR, ANGLE if result == "angle" else dim)

    return rule


def _sqrt(call: CallContext) -> Node:
    a = call.arg("a", what="the argument of sqrt()")
    return call.op("sqrt", [a], SCALAR, a.dim ** Fraction(1, 2) if a.dim is not None else None)


def _abs(call: CallContext) -> Node:
    a = call.arg("a", what="the argument of abs()")
    return call.op("abs", [a], SCALAR, a.dim)


def _minmax(call: CallContext) -> Node:
    op = call.name
    a = call.arg("a", what=f"the arguments of {op}()")
    b = call.arg("b", what=f"the arguments of {op}()")
    ok, dim = unify(a.dim, b.dim)
    if not ok:
        raise UnitError(f"{op}() needs arguments of one unit, got {describe(a.dim)} and {describe(b.dim)}", call.span)
    note_use(a, dim)
    note_use(b, dim)
    return call.op(op, [a, b], SCALAR, dim)


def _norm(call: CallContext) -> Node:
    v = call.compile("v")
    if v.kind != VECTOR:
        raise MdlTypeError(f"norm() takes a vector, got {describe_kind(v)}", call.bound["v"].span)
    return call.op("norm", [v], SCALAR, v.dim)


def _dot_cross(call: CallContext) -> Node:
    op = call.name
    u = call.compile("a")
    v = call.compile("b")
    if u.kind != VECTOR or v.kind != VECTOR or u.size != v.size or (op == "cross" and u.size != 3):
        raise MdlTypeError(f"{op}() takes two vectors of the same size{' (3)' if op == 'cross' else ''}", call.span)
    dim = product_dim(u.dim, v.dim)
    return call.op(op, [u, v], SCALAR if op == "dot" else VECTOR, dim, 0 if op == "dot" else 3)


def _translate(call: CallContext) -> Node:
    b = call.bound
    if "y" not in b and "z" not in b:
        v = call.arg("x", kind=VECTOR, size=3, dim=LENGTH, what="translate((x, y, z))")
        return call.op("translate", [v], TRANSFORM, None)
    items = []
    for key in ("x", "y", "z"):
        if key not in b:
            raise ArgumentError("translate() takes x, y, z or one vector (x, y, z)", call.span)
        items.append(call.arg(key, dim=LENGTH, what=f"translate() argument '{key}'"))
    v = call.op("vec", items, VECTOR, LENGTH, 3)
    return call.op("translate", [v], TRANSFORM, None)


def _rot(call: CallContext) -> Node:
    a = call.arg("angle", dim=ANGLE, what=f"{call.name}() angle")
    return call.op(call.name, [a], TRANSFORM, None)


def _rpy(call: CallContext) -> Node:
    args = [call.arg(k, dim=ANGLE, what=f"rpy() {k}") for k in ("roll", "pitch", "yaw")]
    return call.op("rpy", args, TRANSFORM, None)


def _pose(call: CallContext) -> Node:
    xyz = [call.arg(k, dim=LENGTH, what=f"pose() {k}") for k in ("x", "y", "z")]
    angles = [call.arg(k, dim=ANGLE, what=f"pose() {k}") for k in ("roll", "pitch", "yaw")]
    t = call.op("translate", [call.op("vec", xyz, VECTOR, LENGTH, 3)], TRANSFORM, None)
    return call.op("compose", [t, call.op("rpy", angles, TRANSFORM, None)], TRANSFORM, None)


def _axis_angle(call: CallContext) -> Node:
    axis = call.axis("axis")
    angle = call.arg("angle", dim=ANGLE, what="axis_angle() angle")
    return call.op("axis_angle", [axis, angle], TRANSFORM, None)


def _quat(call: CallContext) -> Node:
    args = [call.arg(k, dim=DIMENSIONLESS, what=f"quat() {k}") for k in ("w", "x", "y", "z")]
    return call.op("quat", args, TRANSFORM, None)


def _look_at(call: CallContext) -> Node:
    eye = call.arg("eye", kind=VECTOR, size=3, dim=LENGTH, what="look_at() eye")
    target = call.arg("target", kind=VECTOR, size=3, dim=LENGTH, what="look_at() target")
    up = call.axis("up") if "up" in call.bound else Const(kind=VECTOR, dim=None, size=3, value=np.array([0, 0, 1.0]))
    if isinstance(eye, Const) and isinstance(target, Const) and isinstance(up, Const):
        problem = look_at_problem(eye.value, target.value, up.value)
        if problem is not None:
            message, hint = problem
            raise DimensionError(message, call.span, hint=hint)
    return call.op("look_at", [eye, target, up], TRANSFORM, None)


_AXIS_NAMES: dict[tuple[float, ...], str] = {
    (1.0, 0.0, 0.0): "x",
    (0.0, 1.0, 0.0): "y",
    (0.0, 0.0, 1.0): "z",
    (-1.0, 0.0, 0.0): "-x",
    (0.0, -1.0, 0.0): "-y",
    (0.0, 0.0, -1.0): "-z",
}


def look_at_problem(eye: Any, target: Any, up: Any) -> tuple[str, str | None] | None:
    """Why ``look_at(eye, target, up)`` has no pose, as a message and a hint: ``eye`` and
    ``target`` the same point, or the view from one to the other parallel to ``up`` (the
    camera's x axis, across both, is then undefined); None when neither.  The checker calls it for constant arguments
    and, for arguments that depend on parameters, at the nominal values
    (:func:`mbcal.language.check.check_at_nominal`)."""
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 m: not this check's to report
        view = target - eye
        n, m = float(np.linalg.norm(view)), float(np.linalg.norm(up))
    if not (np.isfinite(n) and np.isfinite(m) and m > 0):
        return None
    if n == 0:
        return "look_at()'s eye and target are the same point: there is no direction to look in", None
    if float(np.linalg.norm(np.cross(view / n, up / m))) > 1e-12:
        return None
    unit = tuple(float(v) for v in np.round(up / m, 12))
    shown = _AXIS_NAMES.get(unit) or "(" + ", ".join(f"{v:g}" for v in unit) + ")"
    return (
        f"look_at()'s view from eye to target is parallel to its up = {shown}, so the camera's x axis "
        "(perpendicular to both) is undefined",
        "give look_at another up = ... (up = y, say, for a view straight down or up)",
    )


# ---- numeric implementations that are more than one line ------------------------------------------


# By selection: the derivative of xp.minimum is found by an equality test that XLA's rounding
# can defeat inside jit (see mbcal.geometry.raycast).
def _min_array(xp: Any, *a: Any) -> Any:
    return sm.fold(lambda u, v: xp.where(u <= v, u, v), a)


def _max_array(xp: Any, *a: Any) -> Any:
    return sm.fold(lambda u, v: xp.where(u >= v, u, v), a)


def _norm_array(xp: Any, v: Any) -> Any:
    return xp.sqrt(xp.sum(v * v))


# ---- the built-in functions -----------------------------------------------------------------------

_TRIG = _scalar_rule(ANGLE, DIMENSIONLESS, accept=(DIMENSIONLESS,))
_INVERSE_TRIG = _scalar_rule(DIMENSIONLESS, ANGLE)
_PLAIN = _scalar_rule(DIMENSIONLESS, DIMENSIONLESS)
_A = ["a"]
_AB = ["a", "b"]


def _builtin(
    name: str,
    parameters: Sequence[str | tuple[str, bool]],
    typing: TypingRule,
    array: ArrayImplementation | None = None,
    soa: SoaImplementation | None = None,
) -> None:
    _register(name, parameters, typing, array, soa, builtin=True)


# The order is the order of suggestions for a misspelt name.
_builtin("sin", _A, _TRIG, lambda xp, a: xp.sin(a), sm.sin)
_builtin("cos", _A, _TRIG, lambda xp, a: xp.cos(a), sm.cos)
_builtin("tan", _A, _TRIG, lambda xp, a: xp.tan(a))
_builtin("asin", _A, _INVERSE_TRIG, lambda xp, a: xp.arcsin(a))
_builtin("acos", _A, _INVERSE_TRIG, lambda xp, a: xp.arccos(a))
_builtin("atan", _A, _INVERSE_TRIG, lambda xp, a: xp.arctan(a))
_builtin("atan2", _AB, _same_unit_rule("angle"), lambda xp, a, b: xp.arctan2(a, b))
_builtin("exp", _A, _PLAIN, lambda xp, a: xp.exp(a))
_builtin("log", _A, _PLAIN, lambda xp, a: xp.log(a))
_builtin("sqrt", _A, _sqrt, lambda xp, a: xp.sqrt(a))
_builtin("abs", _A, _abs, lambda xp, a: xp.abs(a))
_builtin("min", _AB, _minmax, _min_array, lambda *a: sm.fold(sm.minimum, a))
_builtin("max", _AB, _minmax, _max_array, lambda *a: sm.fold(sm.maximum, a))
_builtin(
    "hypot",
    _AB,
    _same_unit_rule(),
    lambda xp, a, b: xp.sqrt(a * a + b * b),
    lambda a, b: sm.sqrt(sm.add(sm.mul(a, a), sm.mul(b, b))),
)
_builtin("norm", ["v"], _norm, _norm_array, lambda v: sm.sqrt(sm.total(sm.mul(c, c) for c in v)))
_builtin("dot", _AB, _dot_cross, lambda xp, a, b: xp.sum(a * b), lambda a, b: sm.total(map(sm.mul, a, b)))
_builtin("cross", _AB, _dot_cross, lambda xp, a, b: xp.cross(a, b), sm.cross)
_builtin(
    "translate",
    ["x", ("y", False), ("z", False)],
    _translate,
    lambda xp, v: geo.translation(xp, v),
    lambda v: (sm.I3, tuple(v)),
)
_builtin("rot_x", ["angle"], _rot, geo.rot_x, lambda a: sm.rotation(0, a))
_builtin("rot_y", ["angle"], _rot, geo.rot_y, lambda a: sm.rotation(1, a))
_builtin("rot_z", ["angle"], _rot, geo.rot_z, lambda a: sm.rotation(2, a))
_builtin("rpy", ["roll", "pitch", "yaw"], _rpy, geo.rpy, sm.rpy)
_builtin("pose", ["x", "y", "z", "roll", "pitch", "yaw"], _pose)
_builtin("axis_angle", ["axis", "angle"], _axis_angle, geo.axis_angle, sm.axis_angle)
_builtin("quat", ["w", "x", "y", "z"], _quat, geo.quaternion, sm.quaternion)
_builtin("look_at", ["eye", "target", ("up", False)], _look_at, geo.look_at, sm.look_at)
