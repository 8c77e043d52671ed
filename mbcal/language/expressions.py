"""Expressions → typed expression graphs: names, kinds, units, function calls and folding.

A :class:`Compiler` turns syntax-tree expressions into :mod:`mbcal.language.graph` nodes.  It
resolves names through the :class:`~mbcal.language.scope.Namespace` (compiling a ``let`` or
template argument on first use, and a parameter's declaration on first reference), checks the
kinds and units of operators, types calls through the function catalogue
(:mod:`mbcal.language.functions`), and folds everything that does not depend on a parameter
into a constant (:func:`mbcal.language.ir.make_op`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from mbcal.errors import DimensionError, MdlError, MdlTypeError, SourceSpan, UndefinedNameError, UnitError, suggest
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.functions import function_names, get_function
from mbcal.language.graph import (
    SCALAR,
    TRANSFORM,
    VECTOR,
    Const,
    Node,
    ParamRef,
    depends_on,
    describe_kind,
    note_use,
    product_dim,
    quotient_dim,
)
from mbcal.language.ir import make_op
from mbcal.language.model import ParamInfo
from mbcal.language.scope import AXES, Lazy, Namespace, ParamDecl, Scope
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH, UNITS, Dim, describe, fits, unify, within

__all__ = ["Compiler", "AXES", "literal_unit"]


def _infinity(expr: ast.Expr) -> int | None:
    """+1 for ``inf``, -1 for ``-inf`` (an open end of ``limits [a, b]``), else None."""
    if isinstance(expr, ast.Name) and expr.name == "inf":
        return 1
    if isinstance(expr, ast.Unary) and expr.op == "-" and isinstance(expr.operand, ast.Name):
        return -1 if expr.operand.name == "inf" else None
    return None


class Compiler:
    """Compiles the expressions of one model; shared by every statement of the second pass.

    Parameters
    ----------
    names : Namespace
        What the first pass declared.
    """

    def __init__(self, names: Namespace):
        self.names = names
        self.forcing: list[Lazy] = []

    # ---- names -----------------------------------------------------------------------------

    def resolve(self, name: str, scope: Scope, span: SourceSpan) -> Node:
        """The node of a name used in ``scope`` (see :meth:`Namespace.lookup` for the order)."""
        found = self.names.lookup(name, scope, span)
        if isinstance(found, Lazy):
            return self._force(found, span)
        if isinstance(found, ParamDecl):
            return self.param_node(found, span)
        return Const(kind=SCALAR, dim=None, span=span, value=np.asarray(found))

    def _force(self, lazy: Lazy, span: SourceSpan) -> Node:
        if lazy.node is not None:
            return lazy.node
        if lazy.busy:
            cycle = [*self.forcing[self.forcing.index(lazy) :], lazy]
            chain = [lz.what.split("'")[1] for lz in cycle]
            raise MdlError(f"{lazy.what} is defined in terms of itself: {' -> '.join(chain)}", span)
        lazy.busy = True
        self.forcing.append(lazy)
        try:
            lazy.node = self.compile(lazy.expr, lazy.scope)
        finally:
            lazy.busy = False
            self.forcing.pop()
        return lazy.node

    def param_node(self, decl: ParamDecl, span: SourceSpan) -> Node:
        """The :class:`ParamRef` of a parameter, its declaration checked first."""
        self.finish_param(decl, span)
        assert decl.node is not None
        return decl.node

    def finish_param(self, decl: ParamDecl, span: SourceSpan | None = None) -> None:
        """Check a parameter's declaration (value, search range, sigma) and make its node, once.

        Parameters
        ----------
        decl : ParamDecl
            The declaration; ``decl.info`` and ``decl.node`` are set.
        span : SourceSpan, optional
            The reference that needs it, for the error when its value refers to itself.
        """
        if decl.info is not None:
            return
        stmt = decl.stmt
        if decl.busy:
            raise MdlError(f"the value of parameter '{decl.name}' refers to itself", span or stmt.span)
        assert stmt.value is not None
        decl.busy = True
        try:
            value = self.constant(stmt.value, decl.scope, f"the nominal value of parameter '{decl.name}'")
            dim = value.dim
            bounds: list[float | None] = []
            for side, bound in (("lower", stmt.lower), ("upper", stmt.upper)):
                if bound is None:
                    bounds.append(None)
                    continue
                b = self.constant(bound, decl.scope, f"the search range of parameter '{decl.name}'")
                ok, dim2 = unify(dim, b.dim)
                if not ok:
                    raise UnitError(
                        f"the search range of '{decl.name}' is {describe(b.dim)} but its value is {describe(dim)}",
                        bound.span,
                    )
                dim = dim2
                if not math.isfinite(float(b.value)):
                    raise DimensionError(
                        f"the {side} end of the search range of '{decl.name}' is not a finite number", bound.span
                    )
                bounds.append(float(b.value))
            sigma = None
            if stmt.sigma is not None:
                s = self.constant(stmt.sigma, decl.scope, f"the sigma of parameter '{decl.name}'")
                ok, dim2 = unify(dim, s.dim)
                if not ok:
                    raise UnitError(
                        f"the sigma of '{decl.name}' is {describe(s.dim)} but its value is {describe(dim)}",
                        stmt.sigma.span,
                    )
                dim = dim2
                sigma = float(s.value)
                if not math.isfinite(sigma):
                    raise DimensionError(f"the sigma of '{decl.name}' is not a finite number", stmt.sigma.span)
                if not sigma > 0:
                    raise DimensionError(f"sigma must be positive, got {sigma:g}", stmt.sigma.span)
            lower, upper = bounds
            nominal = float(value.value)
            if value.kind != SCALAR:
                raise MdlTypeError(f"a parameter is a number, got a {value.kind}", stmt.value.span)
            if lower is not None and upper is not None and not lower <= upper:
                raise DimensionError(
                    f"empty search range {shown_range(lower, stmt.lower, upper, stmt.upper, dim)} for "
                    f"'{decl.name}' (lower bound above upper)",
                    stmt.lower.span if stmt.lower else stmt.span,
                )
            if not math.isfinite(nominal):
                raise DimensionError(f"the value of '{decl.name}' is not a finite number", stmt.value.span)
            limits, dim = self._limits(decl, dim, lower, upper, nominal)
            decl.info = ParamInfo(
                name=decl.name,
                index=decl.index,
                nominal=nominal,
                lower=lower,
                upper=upper,
                sigma=sigma,
                per_configuration=stmt.per_configuration,
                dim=dim,
                span=stmt.span,
                value_span=stmt.value.span,
                value_unit=literal_unit(stmt.value),
                editable=not decl.scope.in_template and stmt.index_range is None,
                limit_lower=limits[0],
                limit_upper=limits[1],
            )
            decl.node = ParamRef(kind=SCALAR, dim=dim, index=decl.index, name=decl.name)
        finally:
            decl.busy = False

    def _limits(
        self, decl: ParamDecl, dim: Dim | None, lower: float | None, upper: float | None, nominal: float
    ) -> tuple[tuple[float | None, float | None], Dim | None]:
        """A parameter's hard limits (``in [lo, hi] bounded`` or ``limits [a, b]``), checked
        against its unit, its nominal value and its search range."""
        stmt = decl.stmt
        where = stmt.limits_span or stmt.span
        if stmt.bounded and stmt.limit_lower is not None:
            raise MdlError(
                f"'{decl.name}' has both 'bounded' and 'limits [...]': give one",
                where,
                hint="'bounded' makes the search range the limits; 'limits [a, b]' gives other limits",
            )
        if stmt.bounded:
            assert lower is not None and upper is not None  # the grammar puts 'bounded' after a range
            if not lower < upper:
                shown = shown_range(lower, stmt.lower, upper, stmt.upper, dim)
                raise DimensionError(f"'{decl.name}' is bounded by an empty range {shown}", where)
            limits: tuple[float | None, float | None] = (lower, upper)
        elif stmt.limit_lower is not None and stmt.limit_upper is not None:
            ends: list[float | None] = []
            for side, expr in (("lower", stmt.limit_lower), ("upper", stmt.limit_upper)):
                sign = _infinity(expr)
                if sign is not None:
                    if (sign > 0) != (side == "upper"):
                        raise DimensionError(
                            f"the {side} limit of '{decl.name}' cannot be {'' if sign > 0 else '-'}inf "
                            f"(write {'-inf' if side == 'lower' else 'inf'} for no {side} limit)",
                            expr.span,
                        )
                    ends.append(None)
                    continue
                b = self.constant(expr, decl.scope, f"the limits of parameter '{decl.name}'")
                ok, dim2 = unify(dim, b.dim)
                if not ok or b.kind != SCALAR:
                    raise UnitError(
                        f"the limits of '{decl.name}' are {describe(b.dim)} but its value is {describe(dim)}",
                        expr.span,
                    )
                dim = dim2
                value = float(b.value)
                if not math.isfinite(value):
                    raise DimensionError(f"the {side} limit of '{decl.name}' is not a finite number", expr.span)
                ends.append(value)
            limits = (ends[0], ends[1])
            if limits[0] is not None and limits[1] is not None and not limits[0] < limits[1]:
                shown = shown_range(limits[0], stmt.limit_lower, limits[1], stmt.limit_upper, dim)
                raise DimensionError(
                    f"empty limits {shown} for '{decl.name}' (the lower limit must be below the upper)",
                    where,
                )
        else:
            return (None, None), dim
        lo = -math.inf if limits[0] is None else limits[0]
        hi = math.inf if limits[1] is None else limits[1]
        shown = shown_limits(lo, hi, stmt, dim)
        if not within(nominal, lo, hi):
            raise DimensionError(
                f"the value {written(nominal, stmt.value, dim)} of '{decl.name}' lies outside its limits {shown}",
                stmt.value.span if stmt.value is not None else where,
            )
        if lower is not None and upper is not None and not (within(lower, lo, hi) and within(upper, lo, hi)):
            raise DimensionError(
                f"the search range {shown_range(lower, stmt.lower, upper, stmt.upper, dim)} of '{decl.name}' "
                f"reaches outside its limits {shown}",
                stmt.lower.span if stmt.lower is not None else where,
                hint="random starts are drawn inside both: make the search range part of the limits",
            )
        return limits, dim

    def constant(self, expr: ast.Expr, scope: Scope, what: str) -> Const:
        """Compile a scalar that must not depend on a parameter (``what`` names it in errors)."""
        node = self.compile(expr, scope)
        if not isinstance(node, Const):
            params = self.names.params
            deps = [n for n in params if params[n].index in depends_on(node)]
            raise MdlError(
                f"{what} must be a constant, but it depends on parameter '{deps[0] if deps else '?'}'", expr.span
            )
        if node.kind != SCALAR:
            raise MdlTypeError(f"{what} must be a number, got a {node.kind}", expr.span)
        return node

    # ---- expressions -----------------------------------------------------------------------

    def compile(self, expr: ast.Expr, scope: Scope) -> Node:
        """The typed node of an expression used in ``scope``.

        Raises
        ------
        MdlError
            An undefined name, a kind or unit that does not fit, a bad call.
        """
        span = expr.span
        if isinstance(expr, ast.Number):
            if not math.isfinite(expr.value):
                raise MdlError("number is too large", span)
            if expr.unit is None:
                return Const(kind=SCALAR, dim=None, span=span, value=np.asarray(expr.value))
            factor, dim = UNITS[expr.unit]
            return Const(kind=SCALAR, dim=dim, span=span, value=np.asarray(expr.value * factor))
        if isinstance(expr, ast.Name):
            return self.resolve(expr.name, scope, span)
        if isinstance(expr, ast.Unary):
            assert expr.operand is not None
            a = self.compile(expr.operand, scope)
            if a.kind == TRANSFORM:
                raise MdlTypeError("cannot negate a transform", span)
            return make_op("neg", [a], a.kind, a.dim, a.size, span)
        if isinstance(expr, ast.Binary):
            return self._binary(expr, scope)
        if isinstance(expr, ast.Vector):
            items = [self.compile(i, scope) for i in expr.items]
            return self._vector(items, expr.items, span)
        if isinstance(expr, ast.Call):
            return self._call(expr, scope)
        if isinstance(expr, ast.List):
            raise MdlTypeError("a list [...] is allowed only as an argument that takes a list", span)
        if isinstance(expr, ast.String):
            raise MdlTypeError("a string is allowed only as a file name", span)
        raise MdlError(f"unsupported expression {type(expr).__name__}", span)  # pragma: no cover

    def _vector(self, items: list[Node], exprs: Sequence[ast.Expr], span: SourceSpan) -> Node:
        dim: Dim | None = None
        for node, e in zip(items, exprs):
            if node.kind != SCALAR:
                raise MdlTypeError(f"a vector's components are numbers, got a {node.kind}", e.span)
            ok, dim2 = unify(dim, node.dim)
            if not ok:
                raise UnitError(
                    f"vector components have different units: {describe(dim)} and {describe(node.dim)}", e.span
                )
            dim = dim2
        return make_op("vec", items, VECTOR, dim, len(items), span)

    def _binary(self, expr: ast.Binary, scope: Scope) -> Node:
        assert expr.left is not None and expr.right is not None
        a = self.compile(expr.left, scope)
        b = self.compile(expr.right, scope)
        op, span = expr.op, expr.span
        if op in "+-":
            if a.kind != b.kind or a.size != b.size or a.kind == TRANSFORM:
                raise MdlTypeError(
                    f"cannot {'add' if op == '+' else 'subtract'} {describe_kind(a)} and {describe_kind(b)}", span
                )
            ok, dim = unify(a.dim, b.dim)
            if not ok:
                verb = "add" if op == "+" else "subtract"
                raise UnitError(f"cannot {verb} {describe(a.dim)} and {describe(b.dim)}", span)
            note_use(a, dim)  # a term beside 5 cm is a length
            note_use(b, dim)
            return make_op("add" if op == "+" else "sub", [a, b], a.kind, dim, a.size, span)
        if op == "*":
            if a.kind == TRANSFORM and b.kind == TRANSFORM:
                return make_op("compose", [a, b], TRANSFORM, None, 0, span)
            if TRANSFORM in (a.kind, b.kind) and VECTOR in (a.kind, b.kind):
                # In a product of poses a position (x, y, z) stands for translate(x, y, z).
                v, v_expr = (a, expr.left) if a.kind == VECTOR else (b, expr.right)
                if v.size != 3 or not fits(v.dim, LENGTH):
                    raise MdlTypeError(
                        f"in a product of transforms a vector is a translation (x, y, z), got {describe_kind(v)} of "
                        f"{describe(v.dim)}",
                        v_expr.span,
                    )
                note_use(v, LENGTH)
                t = make_op("translate", [v], TRANSFORM, None, 0, v_expr.span)
                a, b = (t, b) if a.kind == VECTOR else (a, t)
                return make_op("compose", [a, b], TRANSFORM, None, 0, span)
            if TRANSFORM in (a.kind, b.kind):
                raise MdlTypeError(
                    f"cannot multiply {describe_kind(a)} by {describe_kind(b)} (a transform is multiplied by a "
                    "transform, or by a position (x, y, z) that stands for a translation)",
                    span,
                )
            if a.kind == VECTOR and b.kind == VECTOR:
                raise MdlTypeError(
                    f"cannot multiply {describe_kind(a)} by {describe_kind(b)} (use dot() or cross())", span
                )
            kind, size = (VECTOR, max(a.size, b.size)) if VECTOR in (a.kind, b.kind) else (SCALAR, 0)
            return make_op("mul", [a, b], kind, product_dim(a.dim, b.dim), size, span)
        if op == "/":
            if b.kind != SCALAR or a.kind == TRANSFORM:
                raise MdlTypeError(f"cannot divide {describe_kind(a)} by {describe_kind(b)}", span)
            return make_op("div", [a, b], a.kind, quotient_dim(a.dim, b.dim), a.size, span)
        if op == "^":
            if a.kind != SCALAR or b.kind != SCALAR:
                raise MdlTypeError("'^' needs numbers on both sides", span)
            if not fits(b.dim, DIMENSIONLESS):
                raise UnitError(f"an exponent must be a plain number, got {describe(b.dim)}", expr.right.span)
            dim = a.dim
            if a.dim is not None and not a.dim.is_dimensionless:
                if not isinstance(b, Const):
                    raise UnitError(f"{describe(a.dim)} can only be raised to a constant power", expr.right.span)
                dim = a.dim ** float(b.value)
            return make_op("pow", [a, b], SCALAR, dim, 0, span)
        raise MdlError(f"unknown operator {op}", span)  # pragma: no cover

    def _call(self, expr: ast.Call, scope: Scope) -> Node:
        function = get_function(expr.func)
        if function is None:
            if expr.func in self.names.templates:
                raise MdlTypeError(
                    f"'{expr.func}' is a template, not a function",
                    expr.span,
                    hint=f"a template is instantiated as a frame: object NAME = {expr.func}(...)",
                )
            hint = suggest(expr.func, list(function_names()) + list(self.names.templates))
            raise UndefinedNameError(f"unknown function '{expr.func}'", expr.span, hint=hint)
        bound = bind(expr.func, function.parameters, expr.args, expr.kwargs, expr.span)
        return function.typing(_Call(self, expr.func, bound, scope, expr.span))

    def arg(
        self,
        bound: Mapping[str, ast.Expr],
        name: str,
        scope: Scope,
        *,
        kind: str = SCALAR,
        dim: Dim | None = None,
        size: int = 0,
        what: str = "",
    ) -> Node | None:
        """Compile argument ``name`` (None when absent), checking its kind, size and unit.

        Parameters
        ----------
        bound : mapping
            Arguments by name, as :func:`mbcal.language.arguments.bind` returns them.
        name : str
            The argument.
        scope : Scope
            Where the call stands.
        kind, dim, size : optional
            What the argument must be: its kind, its dimension (None: any) and, for a vector,
            its size (0: any).
        what : str, optional
            The argument in error messages (default ``'name'``).

        Returns
        -------
        Node or None
            None when the argument is not given.
        """
        expr = bound.get(name)
        if expr is None:
            return None
        node = self.compile(expr, scope)
        label = what or f"'{name}'"
        if node.kind != kind or (size and node.size != size):
            want = f"a {size}-vector" if kind == VECTOR and size else f"a {kind}"
            raise MdlTypeError(f"{label} must be {want}, got {describe_kind(node)}", expr.span)
        if dim is not None and not fits(node.dim, dim):
            raise UnitError(f"{label} must be {describe(dim)}, got {describe(node.dim)}", expr.span)
        note_use(node, dim)
        return node

    def axis(self, expr: ast.Expr, scope: Scope) -> Node:
        """An axis: ``x``, ``y``, ``z``, ``-x``, ... or a non-zero 3-vector (normalised)."""
        sign, inner = 1.0, expr
        if isinstance(expr, ast.Unary) and isinstance(expr.operand, ast.Name):
            sign, inner = -1.0, expr.operand
        if isinstance(inner, ast.Name) and inner.name in AXES:
            return Const(kind=VECTOR, dim=None, size=3, span=expr.span, value=sign * np.asarray(AXES[inner.name]))
        node = self.compile(expr, scope)
        if node.kind != VECTOR or node.size != 3:
            raise MdlTypeError(f"an axis is x, y, z or a 3-vector, got {describe_kind(node)}", expr.span)
        if isinstance(node, Const):
            n = float(np.linalg.norm(node.value))
            if not n > 0 or not math.isfinite(n):
                raise DimensionError("an axis must not be the zero vector", expr.span)
            return Const(kind=VECTOR, dim=None, size=3, span=expr.span, value=node.value / n)
        norm = make_op("norm", [node], SCALAR, node.dim, 0, expr.span)
        return make_op("div", [node, norm], VECTOR, None, 3, expr.span)

    def expect(self, node: Node, kind: str, size: int, dim: Dim | None, what: str, span: SourceSpan) -> None:
        """Refuse a compiled node of another kind, size or unit (``what`` names it in errors)."""
        if node.kind != kind or (size and node.size != size):
            want = f"a {size}-vector" if kind == VECTOR else f"a {kind}"
            raise MdlTypeError(f"{what} must be {want}, got {describe_kind(node)}", span)
        if dim is not None and not fits(node.dim, dim):
            raise UnitError(f"{what} must be {describe(dim)}, got {describe(node.dim)}", span)
        note_use(node, dim)

    def pose(self, expr: ast.Expr, scope: Scope) -> Node:
        """The transform written after ``at``: a transform, or a position (x, y, z) in length units."""
        node = self.compile(expr, scope)
        if node.kind == VECTOR and node.size == 3:
            if not fits(node.dim, LENGTH):
                raise UnitError(f"a position must be {describe(LENGTH)}, got {describe(node.dim)}", expr.span)
            note_use(node, LENGTH)
            return make_op("translate", [node], TRANSFORM, None, 0, expr.span)
        if node.kind != TRANSFORM:
            raise MdlTypeError(
                "'at' needs a transform (translate(...), rot_z(...), ...) or a position (x, y, z), "
                f"got {describe_kind(node)}",
                expr.span,
            )
        return node


class _Call:
    """One call as its typing rule sees it (:class:`mbcal.language.functions.CallContext`)."""

    def __init__(self, compiler: Compiler, name: str, bound: dict[str, ast.Expr], scope: Scope, span: SourceSpan):
        self.compiler = compiler
        self.name = name
        self.bound: Mapping[str, ast.Expr] = bound
        self.scope = scope
        self.span = span

    def arg(self, key: str, *, kind: str = SCALAR, dim: Dim | None = None, size: int = 0, what: str = "") -> Node:
        node = self.compiler.arg(self.bound, key, self.scope, kind=kind, dim=dim, size=size, what=what)
        if node is None:
            raise KeyError(f"{self.name}(): argument '{key}' is not given")
        return node

    def compile(self, key: str) -> Node:
        return self.compiler.compile(self.bound[key], self.scope)

    def axis(self, key: str) -> Node:
        return self.compiler.axis(self.bound[key], self.scope)

    def op(self, name: str, args: Sequence[Node], kind: str, dim: Dim | None, size: int = 0) -> Node:
        return make_op(name, args, kind, dim, size, self.span)


def shown_limits(lo: float | None, hi: float | None, stmt: ast.Param, dim: Dim | None) -> str:
    """A parameter's hard limits for messages, as its declaration wrote them: ``[-60 deg, 60 deg]``."""
    written_lo, written_hi = (stmt.lower, stmt.upper) if stmt.bounded else (stmt.limit_lower, stmt.limit_upper)
    return shown_range(-math.inf if lo is None else lo, written_lo, math.inf if hi is None else hi, written_hi, dim)


def shown_range(lo: float, lo_expr: ast.Expr | None, hi: float, hi_expr: ast.Expr | None, dim: Dim | None) -> str:
    """``[lo, hi]`` for messages, each end as the model wrote it (:func:`written`)."""
    return f"[{written(lo, lo_expr, dim)}, {written(hi, hi_expr, dim)}]"


def written(value: float, expr: ast.Expr | None, dim: Dim | None) -> str:
    """``value`` (SI) as the model wrote it, for messages: in the unit of its literal (``-60 deg``,
    ``5 cm``), else in SI with the unit of its dimension (``0.3 m``, ``1.0472 rad``).  Messages
    gave the SI numbers alone ("the value 1.74533 of 'a' lies outside its limits [-1.0472,
    1.0472]" for ``100 deg limits [-60 deg, 60 deg]``)."""
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    # 12 digits: a value just outside a limit reads so (60.00001 deg, not 60 deg), and the unit's
    # conversion leaves no trace (59.99999999999999 reads 60)
    unit = literal_unit(expr)
    if unit in UNITS:
        return f"{value / UNITS[unit][0]:.12g} {unit}"
    si = {LENGTH: "m", ANGLE: "rad"}.get(dim) if dim is not None else None
    return f"{value:.12g} {si}" if si else f"{value:.12g}"


def literal_unit(expr: ast.Expr | None) -> str | None:
    """The unit of a value written as a literal (``25 cm``, ``-5 deg``), else None."""
    if isinstance(expr, ast.Unary) and expr.op == "-":
        expr = expr.operand
    if isinstance(expr, ast.Number):
        return expr.unit
    return None
