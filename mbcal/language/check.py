"""Syntax tree → checked :class:`~mbcal.language.model.Model`.

The checker expands templates and includes, gives every declaration its full dotted name,
resolves every name an expression uses, checks kinds and units, folds constants and checks
dimensions at the nominal parameter values.  Everything a user can get wrong ends in a typed
:class:`~mbcal.errors.MdlError` that points at the offending text.

Name look-up, innermost first:

1. ``let`` definitions and template arguments of the enclosing scopes (a template body sees
   only its own arguments and lets, and global names — not the caller's);
2. parameters, first relative to the enclosing frames (inside ``frame room``, ``x`` finds a
   parameter declared there, ``room.x``), then by their full name;
3. the constant ``pi``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from mbcal.errors import (
    ArgumentError,
    DimensionError,
    DuplicateNameError,
    MdlError,
    MdlTypeError,
    MeshError,
    SourceSpan,
    UndefinedNameError,
    UnitError,
    suggest,
)
from mbcal.language import ast, ir
from mbcal.language.ir import SCALAR, TRANSFORM, VECTOR, Const, Node, ParamRef, make_op
from mbcal.language.model import (
    SHAPE_KINDS,
    CameraInfo,
    FrameInfo,
    JointInfo,
    MeshData,
    Model,
    ParamInfo,
    PointInfo,
    RangeInfo,
    ShapeInfo,
)
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH, UNITS, Dim, describe, fits, unify

__all__ = ["check", "RESERVED"]

RESERVED = frozenset(
    {
        "include", "param", "let", "template", "frame", "object", "link", "shape", "point",
        "joint", "camera", "range", "target", "measure", "override", "at", "in", "sigma", "per",
        "configuration", "pi", "world",
    }
)  # fmt: skip

CONSTANTS = {"pi": math.pi}
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
MAX_TEMPLATE_DEPTH = 64
MAX_FRAMES = 100_000


# ---- scopes and lazily compiled declarations ------------------------------------------------


@dataclass(eq=False)
class _Lazy:
    """A ``let`` or template argument: compiled on first use, once."""

    what: str
    expr: ast.Expr
    scope: _Scope
    node: Node | None = None
    busy: bool = False


@dataclass(eq=False)
class _ParamDecl:
    stmt: ast.Param
    name: str
    scope: _Scope
    index: int
    node: ParamRef | None = None
    info: ParamInfo | None = None
    busy: bool = False


@dataclass(eq=False)
class _Scope:
    path: str  # prefix for names declared here ("" at the top level)
    parent: _Scope | None
    frame: int  # index of the frame statements attach to (-1: world)
    locals: dict[str, _Lazy] = field(default_factory=dict)
    local_spans: dict[str, SourceSpan] = field(default_factory=dict)
    in_template: bool = False

    def join(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name


@dataclass(eq=False)
class _Deferred:
    """A statement whose expressions are compiled once every parameter is declared."""

    stmt: ast.Statement
    scope: _Scope
    frame: int
    name: str = ""


class _Checker:
    def __init__(self, path: str):
        self.path = path
        self.templates: dict[str, ast.Template] = {}
        self.params: dict[str, _ParamDecl] = {}
        self.frames: list[dict] = []  # name, parent, pose expr+scope, joint, keyword, span
        self.frame_index: dict[str, int] = {}
        self.declared: dict[str, SourceSpan] = {}  # frames, points, sensors, shapes by full name
        self.deferred: list[_Deferred] = []
        self.joints: dict[int, _Deferred] = {}
        self.measures: list[str] = []
        self.files: list[str] = [path]
        self.warnings: list[str] = []
        self.overrides: dict[str, tuple[ast.Override, _Scope]] = {}
        self.global_scope = _Scope("", None, -1)
        self.instantiating: list[str] = []
        self.forcing: list[_Lazy] = []
        self.mesh_cache: dict[str, MeshData] = {}

    # ---- pass 1: structure -----------------------------------------------------------------

    def collect_templates(self, statements: Sequence[ast.Statement], top: bool) -> None:
        for stmt in statements:
            if isinstance(stmt, ast.Template):
                if not top:
                    raise MdlError("templates are declared at the top level of a file", stmt.span)
                self._check_simple_name(stmt.name, "template", stmt.name_span or stmt.span)
                if stmt.name in self.templates:
                    first = self.templates[stmt.name].span
                    raise DuplicateNameError(f"template '{stmt.name}' is already declared at {first}", stmt.span)
                self.templates[stmt.name] = stmt
            elif isinstance(stmt, ast.Include):
                if stmt.resolved:
                    self.files.append(stmt.resolved)
                self.collect_templates(stmt.statements, top)
            elif isinstance(stmt, (ast.Frame, ast.Instance)):
                self.collect_templates(stmt.body, False)

    def _check_simple_name(self, name: str, what: str, span: SourceSpan) -> None:
        if "." in name:
            raise MdlError(f"a {what} name cannot contain '.': '{name}'", span)
        if name in RESERVED:
            raise MdlError(f"'{name}' is a reserved word and cannot name a {what}", span)

    def _declare(self, full: str, span: SourceSpan, what: str) -> None:
        if full in self.declared:
            raise DuplicateNameError(f"'{full}' is already declared at {self.declared[full]}", span)
        self.declared[full] = span

    def walk(self, statements: Sequence[ast.Statement], scope: _Scope) -> None:
        for stmt in statements:
            if isinstance(stmt, ast.Include):
                self.walk(stmt.statements, scope)
            elif isinstance(stmt, ast.Template):
                continue  # collected before
            elif isinstance(stmt, ast.Param):
                self._walk_param(stmt, scope)
            elif isinstance(stmt, ast.Let):
                self._check_simple_name(stmt.name, "let", stmt.name_span or stmt.span)
                if stmt.name in scope.locals:
                    first = scope.local_spans[stmt.name]
                    where = stmt.name_span or stmt.span
                    raise DuplicateNameError(f"'{stmt.name}' is already defined at {first}", where)
                scope.locals[stmt.name] = _Lazy(f"let '{stmt.name}'", stmt.value, scope)
                scope.local_spans[stmt.name] = stmt.name_span or stmt.span
            elif isinstance(stmt, ast.Frame):
                index = self._new_frame(stmt.name, scope, stmt.pose, stmt.keyword, stmt.span, stmt.name_span)
                child = _Scope(self.frames[index]["name"], scope, index, in_template=scope.in_template)
                self.walk(stmt.body, child)
            elif isinstance(stmt, ast.Instance):
                self._walk_instance(stmt, scope)
            elif isinstance(stmt, (ast.Shape, ast.Point)):
                name = stmt.name
                if name is not None:
                    self._check_simple_name(name, type(stmt).__name__.lower(), stmt.name_span or stmt.span)
                    self._declare(scope.join(name), stmt.name_span or stmt.span, "name")
                self.deferred.append(_Deferred(stmt, scope, scope.frame, scope.join(name) if name else ""))
            elif isinstance(stmt, ast.Joint):
                if scope.frame < 0:
                    raise MdlError("a joint moves a frame: put it inside 'frame NAME { ... }'", stmt.span)
                if scope.frame in self.joints:
                    first = self.joints[scope.frame].stmt.span
                    raise DuplicateNameError(
                        f"frame '{self.frames[scope.frame]['name']}' already has a joint at {first}", stmt.span
                    )
                self.joints[scope.frame] = _Deferred(stmt, scope, scope.frame)
            elif isinstance(stmt, (ast.Camera, ast.RangeSensor, ast.Target)):
                index = self._new_frame(
                    stmt.name, scope, stmt.pose, type(stmt).__name__.lower(), stmt.span, stmt.name_span
                )
                self.deferred.append(_Deferred(stmt, scope, index, self.frames[index]["name"]))
            elif isinstance(stmt, ast.Override):
                if scope.path or scope.in_template:
                    raise MdlError(
                        "'override' is written at the top level of a file, with the full parameter name", stmt.span
                    )
                if stmt.name in self.overrides:
                    first = self.overrides[stmt.name][0].span
                    raise DuplicateNameError(
                        f"'{stmt.name}' is already overridden at {first}", stmt.name_span or stmt.span
                    )
                self.overrides[stmt.name] = (stmt, scope)
            elif isinstance(stmt, ast.Measure):
                self.measures.extend(k for k in stmt.kinds if k not in self.measures)
            else:  # pragma: no cover - every statement type is handled above
                raise MdlError(f"unsupported statement {type(stmt).__name__}", stmt.span)

    def _new_frame(
        self,
        name: str,
        scope: _Scope,
        pose: ast.Expr | None,
        keyword: str,
        span: SourceSpan,
        name_span: SourceSpan | None = None,
    ) -> int:
        self._check_simple_name(name, "frame", name_span or span)
        full = scope.join(name)
        self._declare(full, name_span or span, "frame")
        if len(self.frames) >= MAX_FRAMES:
            raise MdlError(f"more than {MAX_FRAMES} frames: is a template instantiating itself?", span)
        self.frames.append(
            {"name": full, "parent": scope.frame, "pose": pose, "scope": scope, "keyword": keyword, "span": span}
        )
        self.frame_index[full] = len(self.frames) - 1
        return len(self.frames) - 1

    def _walk_param(self, stmt: ast.Param, scope: _Scope) -> None:
        names = [stmt.name]
        if stmt.index_range is not None:
            lo, hi = stmt.index_range
            names = [f"{stmt.name}{i}" for i in range(lo, hi + 1)]
        if stmt.name in RESERVED:
            raise MdlError(f"'{stmt.name}' is a reserved word and cannot name a parameter", stmt.name_span or stmt.span)
        for name in names:
            full = scope.join(name)
            if full in self.params:
                first = self.params[full].stmt.span
                raise DuplicateNameError(
                    f"parameter '{full}' is already declared at {first}", stmt.name_span or stmt.span
                )
            self.params[full] = _ParamDecl(stmt, full, scope, len(self.params))

    def _walk_instance(self, stmt: ast.Instance, scope: _Scope) -> None:
        template = self.templates.get(stmt.template)
        if template is None:
            raise UndefinedNameError(
                f"no template named '{stmt.template}'",
                stmt.template_span or stmt.span,
                hint=suggest(stmt.template, self.templates),
            )
        if stmt.template in self.instantiating:
            chain = " -> ".join([*self.instantiating, stmt.template])
            raise MdlError(f"template instantiates itself: {chain}", stmt.span)
        if len(self.instantiating) >= MAX_TEMPLATE_DEPTH:
            raise MdlError(f"templates nested deeper than {MAX_TEMPLATE_DEPTH}", stmt.span)
        index = self._new_frame(stmt.name, scope, stmt.pose, stmt.keyword, stmt.span, stmt.name_span)
        full = self.frames[index]["name"]
        inner = _Scope(full, self.global_scope, index, in_template=True)
        signature = [(p.name, p.default is None) for p in template.params]
        bound = _bind(f"template {template.name}", signature, stmt.args, stmt.kwargs, stmt.span)
        for p in template.params:
            if p.name in bound:
                inner.locals[p.name] = _Lazy(f"argument '{p.name}'", bound[p.name], scope)
            else:
                inner.locals[p.name] = _Lazy(f"argument '{p.name}'", p.default, inner)
            inner.local_spans[p.name] = p.span
        self.instantiating.append(stmt.template)
        try:
            self.walk(template.body, inner)
        finally:
            self.instantiating.pop()
        if stmt.body:
            self.walk(stmt.body, _Scope(full, scope, index, in_template=scope.in_template))

    # ---- names -----------------------------------------------------------------------------

    def resolve(self, name: str, scope: _Scope, span: SourceSpan) -> Node:
        s: _Scope | None = scope
        while s is not None:
            if name in s.locals:
                return self._force(s.locals[name], span)
            s = s.parent
        if name in CONSTANTS:
            return Const(kind=SCALAR, dim=None, span=span, value=np.asarray(CONSTANTS[name]))
        s = scope
        while s is not None:
            candidate = s.join(name)
            if candidate in self.params:
                return self._param_node(self.params[candidate], span)
            s = s.parent
        if name in self.params:
            return self._param_node(self.params[name], span)
        raise UndefinedNameError(f"undefined name '{name}'", span, hint=suggest(name, self._visible(scope)))

    def _visible(self, scope: _Scope) -> list[str]:
        names: list[str] = list(self.params) + list(CONSTANTS)
        s: _Scope | None = scope
        while s is not None:
            names.extend(s.locals)
            if s.path:
                names.extend(n[len(s.path) + 1 :] for n in self.params if n.startswith(s.path + "."))
            s = s.parent
        return names

    def _force(self, lazy: _Lazy, span: SourceSpan) -> Node:
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

    def _param_node(self, decl: _ParamDecl, span: SourceSpan) -> Node:
        self._finish_param(decl, span)
        assert decl.node is not None
        return decl.node

    def _finish_param(self, decl: _ParamDecl, span: SourceSpan | None = None) -> None:
        if decl.info is not None:
            return
        stmt = decl.stmt
        if decl.busy:
            raise MdlError(f"the value of parameter '{decl.name}' refers to itself", span or stmt.span)
        decl.busy = True
        try:
            value = self._constant(stmt.value, decl.scope, f"the nominal value of parameter '{decl.name}'")
            dim = value.dim
            bounds = []
            for bound in (stmt.lower, stmt.upper):
                if bound is None:
                    bounds.append(None)
                    continue
                b = self._constant(bound, decl.scope, f"the search range of parameter '{decl.name}'")
                ok, dim2 = unify(dim, b.dim)
                if not ok:
                    raise UnitError(
                        f"the search range of '{decl.name}' is {describe(b.dim)} but its value is {describe(dim)}",
                        bound.span,
                    )
                dim = dim2
                bounds.append(float(b.value))
            sigma = None
            if stmt.sigma is not None:
                s = self._constant(stmt.sigma, decl.scope, f"the sigma of parameter '{decl.name}'")
                ok, dim2 = unify(dim, s.dim)
                if not ok:
                    raise UnitError(
                        f"the sigma of '{decl.name}' is {describe(s.dim)} but its value is {describe(dim)}",
                        stmt.sigma.span,
                    )
                dim = dim2
                sigma = float(s.value)
                if not sigma > 0:
                    raise DimensionError(f"sigma must be positive, got {sigma:g}", stmt.sigma.span)
            lower, upper = bounds
            nominal = float(value.value)
            if value.kind != SCALAR:
                raise MdlTypeError(f"a parameter is a number, got a {value.kind}", stmt.value.span)
            if lower is not None and upper is not None and not lower <= upper:
                raise DimensionError(
                    f"empty search range [{lower:g}, {upper:g}] for '{decl.name}' (lower bound above upper)",
                    stmt.lower.span if stmt.lower else stmt.span,
                )
            if not math.isfinite(nominal):
                raise DimensionError(f"the value of '{decl.name}' is not a finite number", stmt.value.span)
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
                value_unit=_literal_unit(stmt.value),
                editable=not decl.scope.in_template and stmt.index_range is None,
            )
            decl.node = ParamRef(kind=SCALAR, dim=dim, index=decl.index, name=decl.name)
        finally:
            decl.busy = False

    def _apply_overrides(self) -> None:
        from dataclasses import replace

        for name, (stmt, scope) in self.overrides.items():
            decl = self.params.get(name)
            if decl is None:
                raise UndefinedNameError(
                    f"'override' of an undeclared parameter '{name}'",
                    stmt.name_span or stmt.span,
                    hint=suggest(name, self.params),
                )
            info = decl.info
            assert info is not None
            value = self._constant(stmt.value, scope, f"the override of '{name}'")
            if info.dim is not None and not fits(value.dim, info.dim):
                raise UnitError(
                    f"'{name}' is {describe(info.dim)}, the override is {describe(value.dim)}", stmt.value.span
                )
            sigma = info.sigma
            if stmt.sigma is not None:
                s = self._constant(stmt.sigma, scope, f"the sigma of the override of '{name}'")
                if info.dim is not None and not fits(s.dim, info.dim):
                    raise UnitError(f"the sigma of '{name}' must be {describe(info.dim)}", stmt.sigma.span)
                sigma = float(s.value)
                if not sigma > 0:
                    raise DimensionError(f"sigma must be positive, got {sigma:g}", stmt.sigma.span)
            decl.info = replace(
                info,
                nominal=float(value.value),
                sigma=sigma,
                value_span=stmt.value.span,
                value_unit=_literal_unit(stmt.value),
                editable=True,
            )

    def _constant(self, expr: ast.Expr, scope: _Scope, what: str) -> Const:
        node = self.compile(expr, scope)
        if not isinstance(node, Const):
            deps = [n for n in self.params if self.params[n].index in ir.depends_on(node)]
            raise MdlError(
                f"{what} must be a constant, but it depends on parameter '{deps[0] if deps else '?'}'", expr.span
            )
        if node.kind != SCALAR:
            raise MdlTypeError(f"{what} must be a number, got a {node.kind}", expr.span)
        return node

    # ---- expressions -----------------------------------------------------------------------

    def compile(self, expr: ast.Expr, scope: _Scope) -> Node:
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

    def _binary(self, expr: ast.Binary, scope: _Scope) -> Node:
        a = self.compile(expr.left, scope)
        b = self.compile(expr.right, scope)
        op, span = expr.op, expr.span
        if op in "+-":
            if a.kind != b.kind or a.size != b.size or a.kind == TRANSFORM:
                raise MdlTypeError(f"cannot {'add' if op == '+' else 'subtract'} {_kind(b)} and {_kind(a)}", span)
            ok, dim = unify(a.dim, b.dim)
            if not ok:
                verb = "add" if op == "+" else "subtract"
                raise UnitError(f"cannot {verb} {describe(a.dim)} and {describe(b.dim)}", span)
            return make_op("add" if op == "+" else "sub", [a, b], a.kind, dim, a.size, span)
        if op == "*":
            if a.kind == TRANSFORM and b.kind == TRANSFORM:
                return make_op("compose", [a, b], TRANSFORM, None, 0, span)
            if TRANSFORM in (a.kind, b.kind) and VECTOR in (a.kind, b.kind):
                # In a product of poses a position (x, y, z) stands for translate(x, y, z).
                v, v_expr = (a, expr.left) if a.kind == VECTOR else (b, expr.right)
                if v.size != 3 or not fits(v.dim, LENGTH):
                    raise MdlTypeError(
                        f"in a product of transforms a vector is a translation (x, y, z), got {_kind(v)} of "
                        f"{describe(v.dim)}",
                        v_expr.span,
                    )
                t = make_op("translate", [v], TRANSFORM, None, 0, v_expr.span)
                a, b = (t, b) if a.kind == VECTOR else (a, t)
                return make_op("compose", [a, b], TRANSFORM, None, 0, span)
            if TRANSFORM in (a.kind, b.kind) or (a.kind == VECTOR and b.kind == VECTOR):
                raise MdlTypeError(f"cannot multiply {_kind(a)} by {_kind(b)} (use dot() or cross())", span)
            kind, size = (VECTOR, max(a.size, b.size)) if VECTOR in (a.kind, b.kind) else (SCALAR, 0)
            return make_op("mul", [a, b], kind, _mul_dim(a.dim, b.dim), size, span)
        if op == "/":
            if b.kind != SCALAR or a.kind == TRANSFORM:
                raise MdlTypeError(f"cannot divide {_kind(a)} by {_kind(b)}", span)
            return make_op("div", [a, b], a.kind, _div_dim(a.dim, b.dim), a.size, span)
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

    def _call(self, expr: ast.Call, scope: _Scope) -> Node:
        spec = _FUNCTIONS.get(expr.func)
        if spec is None:
            hint = suggest(expr.func, list(_FUNCTIONS) + list(self.templates))
            extra = ""
            if expr.func in self.templates:
                extra = " (templates are instantiated with 'object NAME = template(...)')"
            raise UndefinedNameError(f"unknown function '{expr.func}'{extra}", expr.span, hint=hint)
        signature, typer = spec
        bound = _bind(expr.func, signature, expr.args, expr.kwargs, expr.span)
        return typer(self, bound, scope, expr.span)

    def arg(
        self,
        bound: dict[str, ast.Expr],
        name: str,
        scope: _Scope,
        *,
        kind: str = SCALAR,
        dim: Dim | None = None,
        size: int = 0,
        what: str = "",
    ) -> Node | None:
        """Compile argument ``name`` (None when absent), checking its kind, size and unit."""
        expr = bound.get(name)
        if expr is None:
            return None
        node = self.compile(expr, scope)
        label = what or f"'{name}'"
        if node.kind != kind or (size and node.size != size):
            want = f"a {size}-vector" if kind == VECTOR and size else f"a {kind}"
            raise MdlTypeError(f"{label} must be {want}, got {_kind(node)}", expr.span)
        if dim is not None and not fits(node.dim, dim):
            raise UnitError(f"{label} must be {describe(dim)}, got {describe(node.dim)}", expr.span)
        return node

    def axis(self, expr: ast.Expr, scope: _Scope) -> Node:
        """An axis: ``x``, ``y``, ``z``, ``-x``, ... or a non-zero 3-vector (normalised)."""
        sign, inner = 1.0, expr
        if isinstance(expr, ast.Unary) and isinstance(expr.operand, ast.Name):
            sign, inner = -1.0, expr.operand
        if isinstance(inner, ast.Name) and inner.name in AXES:
            return Const(kind=VECTOR, dim=None, size=3, span=expr.span, value=sign * np.asarray(AXES[inner.name]))
        node = self.compile(expr, scope)
        if node.kind != VECTOR or node.size != 3:
            raise MdlTypeError(f"an axis is x, y, z or a 3-vector, got {_kind(node)}", expr.span)
        if isinstance(node, Const):
            n = float(np.linalg.norm(node.value))
            if not n > 0 or not math.isfinite(n):
                raise DimensionError("an axis must not be the zero vector", expr.span)
            return Const(kind=VECTOR, dim=None, size=3, span=expr.span, value=node.value / n)
        norm = make_op("norm", [node], SCALAR, node.dim, 0, expr.span)
        return make_op("div", [node, norm], VECTOR, None, 3, expr.span)

    # ---- pass 2: compile deferred statements -----------------------------------------------

    def build(self, statements: Sequence[ast.Statement]) -> Model:
        self.collect_templates(statements, True)
        self.walk(statements, self.global_scope)
        for decl in self.params.values():
            self._finish_param(decl)
        self._apply_overrides()
        frames = []
        for i, f in enumerate(self.frames):
            pose = self._pose(f["pose"], f["scope"]) if f["pose"] is not None else None
            joint = self._joint(self.joints[i]) if i in self.joints else None
            frames.append(FrameInfo(f["name"], f["parent"], pose, joint, f["keyword"], f["span"]))
        points: list[PointInfo] = []
        cameras: list[CameraInfo] = []
        ranges: list[RangeInfo] = []
        shapes: list[ShapeInfo] = []
        shape_counter: dict[int, int] = {}
        targets = []
        for d in self.deferred:
            stmt = d.stmt
            if isinstance(stmt, ast.Point):
                node = self.compile(stmt.value, d.scope)
                self._expect(node, VECTOR, 3, LENGTH, f"point '{stmt.name}'", stmt.value.span)
                points.append(PointInfo(d.name, d.frame, node, stmt.span))
            elif isinstance(stmt, ast.Shape):
                n = shape_counter.get(d.frame, 0)
                shape_counter[d.frame] = n + 1
                name = d.name or d.scope.join(f"shape{n}" if stmt.name is None else stmt.name)
                shapes.append(self._shape(stmt, d.scope, d.frame, name))
            elif isinstance(stmt, ast.Camera):
                cameras.append(self._camera(stmt, d.scope, d.frame, d.name))
            elif isinstance(stmt, ast.RangeSensor):
                ranges.append(self._range(stmt, d.scope, d.frame, d.name))
            elif isinstance(stmt, ast.Target):
                target_pts, target = self._target(stmt, d.scope, d.frame, d.name)
                points.extend(target_pts)
                targets.append(target)
        params = tuple(d.info for d in sorted(self.params.values(), key=lambda d: d.index))
        model = Model(
            path=self.path,
            params=params,  # type: ignore[arg-type]
            frames=tuple(frames),
            points=tuple(points),
            cameras=tuple(cameras),
            ranges=tuple(ranges),
            shapes=tuple(shapes),
            measures=tuple(self.measures),
            targets=tuple(targets),
            templates=tuple(self.templates),
            files=tuple(dict.fromkeys(self.files)),
            warnings=tuple(self.warnings),
        )
        _check_at_nominal(model)
        return model

    def _expect(self, node: Node, kind: str, size: int, dim: Dim | None, what: str, span: SourceSpan) -> None:
        if node.kind != kind or (size and node.size != size):
            want = f"a {size}-vector" if kind == VECTOR else f"a {kind}"
            raise MdlTypeError(f"{what} must be {want}, got {_kind(node)}", span)
        if dim is not None and not fits(node.dim, dim):
            raise UnitError(f"{what} must be {describe(dim)}, got {describe(node.dim)}", span)

    def _pose(self, expr: ast.Expr, scope: _Scope) -> Node:
        node = self.compile(expr, scope)
        if node.kind == VECTOR and node.size == 3:
            if not fits(node.dim, LENGTH):
                raise UnitError(f"a position must be {describe(LENGTH)}, got {describe(node.dim)}", expr.span)
            return make_op("translate", [node], TRANSFORM, None, 0, expr.span)
        if node.kind != TRANSFORM:
            raise MdlTypeError(
                f"'at' needs a transform (translate(...), rot_z(...), ...) or a position (x, y, z), got {_kind(node)}",
                expr.span,
            )
        return node

    def _joint(self, d: _Deferred) -> JointInfo:
        stmt = d.stmt
        assert isinstance(stmt, ast.Joint)
        kinds = {"revolute": ANGLE, "continuous": ANGLE, "prismatic": LENGTH}
        if stmt.kind not in kinds:
            raise MdlError(
                f"unknown joint kind '{stmt.kind}' (revolute, continuous or prismatic)",
                stmt.span,
                hint=suggest(stmt.kind, kinds),
            )
        dim = kinds[stmt.kind]
        signature = [("axis", True), ("q", True), ("offset", False), ("lower", False), ("upper", False)]
        bound = _bind(f"joint {stmt.kind}", signature, stmt.args, stmt.kwargs, stmt.span)
        axis = self.axis(bound["axis"], d.scope)
        q = self.arg(bound, "q", d.scope, dim=dim, what="the joint variable")
        offset = self.arg(bound, "offset", d.scope, dim=dim, what="the joint offset")
        limits = []
        for key in ("lower", "upper"):
            node = self.arg(bound, key, d.scope, dim=dim, what=f"the joint's {key} limit")
            if node is not None and not isinstance(node, Const):
                raise MdlError(f"the joint's {key} limit must be a constant", bound[key].span)
            limits.append(float(node.value) if isinstance(node, Const) else None)
        assert q is not None
        kind = "revolute" if stmt.kind == "continuous" else stmt.kind
        return JointInfo(kind, axis, q, offset, limits[0], limits[1], stmt.span)

    def _shape(self, stmt: ast.Shape, scope: _Scope, frame: int, name: str) -> ShapeInfo:
        kind = stmt.kind
        if kind not in SHAPE_KINDS:
            raise UndefinedNameError(
                f"unknown shape '{kind}' (one of {', '.join(SHAPE_KINDS)})",
                stmt.kind_span or stmt.span,
                hint=suggest(kind, SHAPE_KINDS),
            )
        pose = self._pose(stmt.pose, scope) if stmt.pose is not None else None
        mesh = None
        if kind == "mesh":
            bound = _bind("mesh", [("file", True), ("scale", False)], stmt.args, stmt.kwargs, stmt.span)
            mesh = self._mesh(bound["file"])
            scale_expr = bound.get("scale")
            if scale_expr is None:
                one = Const(kind=SCALAR, dim=None, value=np.asarray(1.0), span=stmt.span)
                dims: tuple[Node, ...] = (one, one, one)
            else:
                scale = self.compile(scale_expr, scope)
                if scale.kind == SCALAR:
                    dims = (scale, scale, scale)
                elif scale.kind == VECTOR and scale.size == 3:
                    dims = tuple(
                        make_op(
                            "dot",
                            [scale, Const(kind=VECTOR, dim=None, size=3, value=np.eye(3)[i])],
                            SCALAR,
                            scale.dim,
                            0,
                            scale_expr.span,
                        )
                        for i in range(3)
                    )
                else:
                    raise MdlTypeError(f"a mesh scale is a number or a 3-vector, got {_kind(scale)}", scale_expr.span)
                if not fits(scale.dim, DIMENSIONLESS):
                    raise UnitError(f"a mesh scale is a plain number, got {describe(scale.dim)}", scale_expr.span)
            return ShapeInfo(name, frame, kind, dims, pose, mesh, stmt.span)
        if kind == "plane" and (stmt.args or stmt.kwargs):
            kind = "rectangle"
        signature = [(n, True) for n in SHAPE_KINDS[kind]]
        bound = _bind(stmt.kind, signature, stmt.args, stmt.kwargs, stmt.span)
        nodes = []
        for n in SHAPE_KINDS[kind]:
            node = self.arg(bound, n, scope, dim=LENGTH, what=f"{stmt.kind}() argument '{n}'")
            assert node is not None
            nodes.append(node)
        return ShapeInfo(name, frame, kind, tuple(nodes), pose, None, stmt.span)

    def _mesh(self, expr: ast.Expr) -> MeshData:
        if not isinstance(expr, ast.String):
            raise MdlTypeError('a mesh needs a file name in quotes: mesh("part.stl")', expr.span)
        base = Path(expr.span.path).resolve().parent if expr.span.path not in ("<string>",) else Path.cwd()
        path = base / expr.value
        key = str(path.resolve())
        if key in self.mesh_cache:
            return self.mesh_cache[key]
        mesh = load_mesh(path, expr.span)
        self.mesh_cache[key] = mesh
        return mesh

    def _camera(self, stmt: ast.Camera, scope: _Scope, frame: int, name: str) -> CameraInfo:
        keys = ["width", "height", "f", "fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3"]
        if stmt.args:
            raise ArgumentError(
                "camera settings are named: camera NAME(width = ..., height = ..., f = ...)", stmt.args[0].span
            )
        bound = _bind(f"camera {stmt.name}", [(k, False) for k in keys], (), stmt.kwargs, stmt.span)
        for required in ("width", "height"):
            if required not in bound:
                raise ArgumentError(f"camera '{stmt.name}' needs '{required}' (image size in pixels)", stmt.span)
        size = []
        for key in ("width", "height"):
            node = self.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"the camera's {key}")
            if not isinstance(node, Const) or float(node.value) != round(float(node.value)) or node.value <= 0:
                raise DimensionError(f"the camera's {key} must be a positive whole number of pixels", bound[key].span)
            size.append(int(node.value))
        f = self.arg(bound, "f", scope, dim=DIMENSIONLESS, what="the focal length f (pixels)")
        fx = self.arg(bound, "fx", scope, dim=DIMENSIONLESS, what="fx (pixels)") or f
        fy = self.arg(bound, "fy", scope, dim=DIMENSIONLESS, what="fy (pixels)") or f
        if fx is None or fy is None:
            raise ArgumentError(f"camera '{stmt.name}' needs a focal length: f = ... or fx = ..., fy = ...", stmt.span)

        def pixel(key: str, default: float) -> Node:
            node = self.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"'{key}'")
            return node if node is not None else Const(kind=SCALAR, dim=None, value=np.asarray(default))

        cx = pixel("cx", (size[0] - 1) / 2.0)
        cy = pixel("cy", (size[1] - 1) / 2.0)
        skew = pixel("skew", 0.0)
        dist = tuple(pixel(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3"))
        return CameraInfo(name, frame, size[0], size[1], (fx, fy, cx, cy, skew), dist, stmt.span)  # type: ignore[arg-type]

    def _const_vectors(self, expr: ast.Expr, scope: _Scope, what: str) -> np.ndarray:
        items = expr.items if isinstance(expr, ast.List) else (expr,)
        out = []
        for item in items:
            node = self.compile(item, scope)
            if not isinstance(node, Const) or node.kind != VECTOR or node.size != 3:
                raise MdlTypeError(f"{what} must be constant 3-vectors", item.span)
            n = float(np.linalg.norm(node.value))
            if not n > 0 or not math.isfinite(n):
                raise DimensionError("a direction must not be the zero vector", item.span)
            out.append(node.value / n)
        if not out:
            raise ArgumentError(f"{what}: the list is empty", expr.span)
        return np.asarray(out, dtype=float)

    def _range(self, stmt: ast.RangeSensor, scope: _Scope, frame: int, name: str) -> RangeInfo:
        if stmt.args:
            raise ArgumentError("range sensor settings are named: range NAME(direction = (0, 0, 1))", stmt.args[0].span)
        keys = [("direction", False), ("directions", False), ("fov", False), ("rays", False), ("max", False)]
        bound = _bind(f"range {stmt.name}", keys, (), stmt.kwargs, stmt.span)
        given = [k for k in ("direction", "directions", "fov") if k in bound]
        if len(given) != 1:
            raise ArgumentError(
                f"range sensor '{stmt.name}' needs exactly one of direction = ..., directions = [...] "
                "or fov = (h, v), rays = (columns, rows)",
                stmt.span,
            )
        if "direction" in bound:
            dirs = self._const_vectors(bound["direction"], scope, "a direction")
            if len(dirs) != 1:
                raise ArgumentError("use 'directions = [...]' for several rays", bound["direction"].span)
        elif "directions" in bound:
            if not isinstance(bound["directions"], ast.List):
                raise MdlTypeError("'directions' takes a list: [(x, y, z), ...]", bound["directions"].span)
            dirs = self._const_vectors(bound["directions"], scope, "each direction")
        else:
            fov = self.arg(bound, "fov", scope, kind=VECTOR, size=2, dim=ANGLE, what="fov (horizontal, vertical)")
            if "rays" not in bound:
                raise ArgumentError("a field of view needs rays = (columns, rows)", stmt.span)
            rays = self.arg(bound, "rays", scope, kind=VECTOR, size=2, dim=DIMENSIONLESS, what="rays (columns, rows)")
            if not isinstance(fov, Const) or not isinstance(rays, Const):
                raise MdlError("fov and rays must be constants", stmt.span)
            cols, rows = (int(round(float(v))) for v in rays.value)
            if cols < 1 or rows < 1 or cols * rows > 1_000_000:
                raise DimensionError("rays must be between 1 and 10^6 in all", bound["rays"].span)
            h = np.tan(np.linspace(-fov.value[0] / 2, fov.value[0] / 2, cols)) if cols > 1 else np.zeros(1)
            v = np.tan(np.linspace(-fov.value[1] / 2, fov.value[1] / 2, rows)) if rows > 1 else np.zeros(1)
            hh, vv = np.meshgrid(h, v)
            d = np.stack([hh.ravel(), vv.ravel(), np.ones(hh.size)], axis=1)
            dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
        max_range = 1e3
        if "max" in bound:
            node = self.arg(bound, "max", scope, dim=LENGTH, what="the maximum range")
            if not isinstance(node, Const) or not float(node.value) > 0:
                raise DimensionError("the maximum range must be a positive constant", bound["max"].span)
            max_range = float(node.value)
        return RangeInfo(name, frame, dirs, max_range, stmt.span)

    def _target(self, stmt: ast.Target, scope: _Scope, frame: int, name: str):
        from mbcal.language.targets import target_points

        return target_points(self, stmt, scope, frame, name)


# ---- helpers ----------------------------------------------------------------------------------


def _literal_unit(expr: ast.Expr | None) -> str | None:
    """The unit of a value written as a literal (``25 cm``, ``-5 deg``), else None."""
    if isinstance(expr, ast.Unary) and expr.op == "-":
        expr = expr.operand
    if isinstance(expr, ast.Number):
        return expr.unit
    return None


def _kind(node: Node) -> str:
    if node.kind == VECTOR:
        return f"a {node.size}-vector"
    return f"a {node.kind}"


def _mul_dim(a: Dim | None, b: Dim | None) -> Dim | None:
    if a is None:
        return b
    if b is None:
        return a
    return a * b


def _div_dim(a: Dim | None, b: Dim | None) -> Dim | None:
    if b is None:
        return a
    return (a if a is not None else DIMENSIONLESS) / b


def _bind(
    fname: str,
    signature: Sequence[tuple[str, bool]],
    args: Sequence[ast.Expr],
    kwargs: Sequence[ast.Keyword],
    span: SourceSpan,
) -> dict[str, ast.Expr]:
    """Match call arguments to a signature [(name, required), ...]; ArgumentError on mismatch."""
    names = [n for n, _ in signature]
    required = [n for n, r in signature if r]
    if len(args) > len(names):
        lo, hi = len(required), len(names)
        takes = f"{hi}" if lo == hi else f"{lo} to {hi}"
        listing = f" ({', '.join(names)})" if names else ""
        raise ArgumentError(
            f"{fname}() takes {takes} argument{'s' if hi != 1 else ''}{listing} but {len(args)} were given",
            args[len(names)].span if len(names) < len(args) else span,
        )
    bound: dict[str, ast.Expr] = dict(zip(names, args))
    for kw in kwargs:
        if kw.name not in names:
            raise ArgumentError(
                f"{fname}() has no argument '{kw.name}' (it takes {', '.join(names) or 'none'})",
                kw.span,
                hint=suggest(kw.name, names),
            )
        if kw.name in bound:
            raise ArgumentError(f"{fname}(): argument '{kw.name}' is given twice", kw.span)
        bound[kw.name] = kw.value
    missing = [n for n in required if n not in bound]
    if missing:
        raise ArgumentError(
            f"{fname}() is missing argument{'s' if len(missing) > 1 else ''} {', '.join(repr(m) for m in missing)}",
            span,
        )
    return bound


# ---- built-in functions: name → (signature, typer) ---------------------------------------------


def _scalar_fn(op: str, arg_dim: Dim | None, result: Dim | None, *, accept: tuple[Dim, ...] = ()):
    def typer(c: _Checker, b, scope, span):
        a = c.arg(b, "a", scope, what=f"the argument of {op}()")
        if arg_dim is not None and not (fits(a.dim, arg_dim) or a.dim in accept):
            raise UnitError(f"{op}() takes {describe(arg_dim)}, got {describe(a.dim)}", b["a"].span)
        return make_op(op, [a], SCALAR, result, 0, span)

    return [("a", True)], typer


def _same_dim_fn(op: str, result: str = "same"):
    def typer(c: _Checker, b, scope, span):
        a = c.arg(b, "a", scope, what=f"the first argument of {op}()")
        bb = c.arg(b, "b", scope, what=f"the second argument of {op}()")
        ok, dim = unify(a.dim, bb.dim)
        if not ok:
            raise UnitError(f"{op}() needs arguments of one unit, got {describe(a.dim)} and {describe(bb.dim)}", span)
        return make_op(op, [a, bb], SCALAR, ANGLE if result == "angle" else dim, 0, span)

    return [("a", True), ("b", True)], typer


def _sqrt(c: _Checker, b, scope, span):
    a = c.arg(b, "a", scope, what="the argument of sqrt()")
    return make_op("sqrt", [a], SCALAR, a.dim ** Fraction(1, 2) if a.dim is not None else None, 0, span)


def _abs(c: _Checker, b, scope, span):
    a = c.arg(b, "a", scope, what="the argument of abs()")
    return make_op("abs", [a], SCALAR, a.dim, 0, span)


def _minmax(op: str):
    def typer(c: _Checker, b, scope, span):
        a = c.arg(b, "a", scope, what=f"the arguments of {op}()")
        bb = c.arg(b, "b", scope, what=f"the arguments of {op}()")
        ok, dim = unify(a.dim, bb.dim)
        if not ok:
            raise UnitError(f"{op}() needs arguments of one unit, got {describe(a.dim)} and {describe(bb.dim)}", span)
        return make_op(op, [a, bb], SCALAR, dim, 0, span)

    return [("a", True), ("b", True)], typer


def _norm(c: _Checker, b, scope, span):
    v = c.compile(b["v"], scope)
    if v.kind != VECTOR:
        raise MdlTypeError(f"norm() takes a vector, got {_kind(v)}", b["v"].span)
    return make_op("norm", [v], SCALAR, v.dim, 0, span)


def _dot_cross(op: str):
    def typer(c: _Checker, b, scope, span):
        u = c.compile(b["a"], scope)
        v = c.compile(b["b"], scope)
        if u.kind != VECTOR or v.kind != VECTOR or u.size != v.size or (op == "cross" and u.size != 3):
            raise MdlTypeError(f"{op}() takes two vectors of the same size{' (3)' if op == 'cross' else ''}", span)
        dim = _mul_dim(u.dim, v.dim)
        return make_op(op, [u, v], SCALAR if op == "dot" else VECTOR, dim, 0 if op == "dot" else 3, span)

    return [("a", True), ("b", True)], typer


def _translate(c: _Checker, b, scope, span):
    if "y" not in b and "z" not in b:
        v = c.arg(b, "x", scope, kind=VECTOR, size=3, dim=LENGTH, what="translate((x, y, z))")
        return make_op("translate", [v], TRANSFORM, None, 0, span)
    items = []
    for key in ("x", "y", "z"):
        if key not in b:
            raise ArgumentError("translate() takes x, y, z or one vector (x, y, z)", span)
        items.append(c.arg(b, key, scope, dim=LENGTH, what=f"translate() argument '{key}'"))
    v = make_op("vec", items, VECTOR, LENGTH, 3, span)
    return make_op("translate", [v], TRANSFORM, None, 0, span)


def _rot(op: str):
    def typer(c: _Checker, b, scope, span):
        a = c.arg(b, "angle", scope, dim=ANGLE, what=f"{op}() angle")
        return make_op(op, [a], TRANSFORM, None, 0, span)

    return [("angle", True)], typer


def _rpy(c: _Checker, b, scope, span):
    args = [c.arg(b, k, scope, dim=ANGLE, what=f"rpy() {k}") for k in ("roll", "pitch", "yaw")]
    return make_op("rpy", args, TRANSFORM, None, 0, span)


def _pose(c: _Checker, b, scope, span):
    xyz = [c.arg(b, k, scope, dim=LENGTH, what=f"pose() {k}") for k in ("x", "y", "z")]
    angles = [c.arg(b, k, scope, dim=ANGLE, what=f"pose() {k}") for k in ("roll", "pitch", "yaw")]
    t = make_op("translate", [make_op("vec", xyz, VECTOR, LENGTH, 3, span)], TRANSFORM, None, 0, span)
    return make_op("compose", [t, make_op("rpy", angles, TRANSFORM, None, 0, span)], TRANSFORM, None, 0, span)


def _axis_angle(c: _Checker, b, scope, span):
    axis = c.axis(b["axis"], scope)
    angle = c.arg(b, "angle", scope, dim=ANGLE, what="axis_angle() angle")
    return make_op("axis_angle", [axis, angle], TRANSFORM, None, 0, span)


def _quat(c: _Checker, b, scope, span):
    args = [c.arg(b, k, scope, dim=DIMENSIONLESS, what=f"quat() {k}") for k in ("w", "x", "y", "z")]
    return make_op("quat", args, TRANSFORM, None, 0, span)


def _look_at(c: _Checker, b, scope, span):
    eye = c.arg(b, "eye", scope, kind=VECTOR, size=3, dim=LENGTH, what="look_at() eye")
    target = c.arg(b, "target", scope, kind=VECTOR, size=3, dim=LENGTH, what="look_at() target")
    up = c.axis(b["up"], scope) if "up" in b else Const(kind=VECTOR, dim=None, size=3, value=np.array([0, 0, 1.0]))
    return make_op("look_at", [eye, target, up], TRANSFORM, None, 0, span)


_FUNCTIONS = {
    "sin": _scalar_fn("sin", ANGLE, DIMENSIONLESS, accept=(DIMENSIONLESS,)),
    "cos": _scalar_fn("cos", ANGLE, DIMENSIONLESS, accept=(DIMENSIONLESS,)),
    "tan": _scalar_fn("tan", ANGLE, DIMENSIONLESS, accept=(DIMENSIONLESS,)),
    "asin": _scalar_fn("asin", DIMENSIONLESS, ANGLE),
    "acos": _scalar_fn("acos", DIMENSIONLESS, ANGLE),
    "atan": _scalar_fn("atan", DIMENSIONLESS, ANGLE),
    "atan2": _same_dim_fn("atan2", "angle"),
    "exp": _scalar_fn("exp", DIMENSIONLESS, DIMENSIONLESS),
    "log": _scalar_fn("log", DIMENSIONLESS, DIMENSIONLESS),
    "sqrt": ([("a", True)], _sqrt),
    "abs": ([("a", True)], _abs),
    "min": _minmax("min"),
    "max": _minmax("max"),
    "hypot": _same_dim_fn("hypot"),
    "norm": ([("v", True)], _norm),
    "dot": _dot_cross("dot"),
    "cross": _dot_cross("cross"),
    "translate": ([("x", True), ("y", False), ("z", False)], _translate),
    "rot_x": _rot("rot_x"),
    "rot_y": _rot("rot_y"),
    "rot_z": _rot("rot_z"),
    "rpy": ([("roll", True), ("pitch", True), ("yaw", True)], _rpy),
    "pose": ([(k, True) for k in ("x", "y", "z", "roll", "pitch", "yaw")], _pose),
    "axis_angle": ([("axis", True), ("angle", True)], _axis_angle),
    "quat": ([("w", True), ("x", True), ("y", True), ("z", True)], _quat),
    "look_at": ([("eye", True), ("target", True), ("up", False)], _look_at),
}

FUNCTION_NAMES = tuple(_FUNCTIONS)


# ---- meshes -------------------------------------------------------------------------------------


def load_mesh(path: Path, span: SourceSpan | None) -> MeshData:
    """Read an STL/OBJ/PLY/glTF file with trimesh; a :class:`MeshError` when it is unusable."""
    import trimesh

    suffix = path.suffix.lower()
    if suffix not in (".stl", ".obj", ".ply", ".glb", ".gltf", ".off", ".dae"):
        raise MeshError(f"unsupported mesh format '{suffix}' (use .stl, .obj, .ply, .glb or .gltf)", span)
    if not path.is_file():
        raise MeshError(f"mesh file not found: {path}", span, hint="mesh paths are relative to the model file")
    if path.stat().st_size == 0:
        raise MeshError(f"mesh file is empty: {path}", span)
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many types for corrupt files
        raise MeshError(f"cannot read mesh {path}: {type(err).__name__}: {err}", span) from None
    vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=float)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int64)
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise MeshError(f"mesh {path} has no triangles", span)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
        raise MeshError(f"mesh {path} has invalid vertices", span)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"mesh {path} has faces that refer to missing vertices", span)
    return MeshData(str(path), vertices, faces)


# ---- checks at the nominal values -----------------------------------------------------------------


def _check_at_nominal(model: Model) -> None:
    """Dimensions must be positive and poses finite at the nominal parameter values."""
    X = model.nominal
    memo: dict[int, object] = {}

    def value(node: Node) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.asarray(ir.evaluate(node, X, memo, np), dtype=float)

    for shape in model.shapes:
        if shape.kind == "mesh":
            for node in shape.dims:
                v = value(node)
                if not (np.isfinite(v) and v > 0):
                    raise DimensionError(f"a mesh scale must be positive, got {float(v):g}", node.span or shape.span)
            continue
        names = SHAPE_KINDS[shape.kind]
        vals = [float(value(n)) for n in shape.dims]
        for n, node, v in zip(names, shape.dims, vals):
            if not (math.isfinite(v) and v > 0):
                raise DimensionError(
                    f"{shape.kind}() dimension '{n}' must be positive, got {v:g} m at the nominal values",
                    node.span or shape.span,
                )
        if shape.kind == "tube" and not vals[1] < vals[0]:
            raise DimensionError(
                f"a tube's inner radius ({vals[1]:g} m) must be smaller than its outer radius ({vals[0]:g} m)",
                shape.dims[1].span or shape.span,
            )
    for cam in model.cameras:
        for key, node in zip(("fx", "fy"), cam.intrinsics[:2]):
            v = float(value(node))
            if not (math.isfinite(v) and v > 0):
                raise DimensionError(f"camera '{cam.name}': {key} must be positive, got {v:g}", node.span or cam.span)
    for frame in model.frames:
        if frame.pose is not None and not np.all(np.isfinite(value(frame.pose))):
            raise DimensionError(
                f"the pose of '{frame.name}' is not finite at the nominal values (a zero axis or quaternion?)",
                frame.pose.span or frame.span,
            )
    for point in model.points:
        if not np.all(np.isfinite(value(point.position))):
            raise DimensionError(f"point '{point.name}' is not finite at the nominal values", point.span)


def check(statements: Sequence[ast.Statement], path: str) -> Model:
    """Check parsed statements and build the :class:`Model`."""
    return _Checker(path).build(statements)
