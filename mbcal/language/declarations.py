"""Second pass of the checker: every declaration compiled into the :class:`Model`.

Parameters first (their values, then ``override``\\ s), then frames with their poses and
joints, then the statements deferred by the first pass — points, shapes
(:mod:`mbcal.language.shapes`), cameras and range sensors (:mod:`mbcal.language.sensors`) and
calibration targets (:mod:`mbcal.language.targets`) — in the order they were written.
"""

from __future__ import annotations

import dataclasses
import math

from mbcal.errors import DimensionError, MdlError, UndefinedNameError, UnitError, suggest
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.expressions import Compiler, literal_unit, shown_limits, written
from mbcal.language.graph import VECTOR, Const, recording_uses
from mbcal.language.model import (
    CameraInfo,
    FrameInfo,
    JointInfo,
    Model,
    PointInfo,
    RangeInfo,
    ShapeInfo,
    TargetInfo,
)
from mbcal.language.scope import Deferred, Namespace, ParamDecl, Scope
from mbcal.language.sensors import camera, range_sensor
from mbcal.language.shapes import ShapeChecker
from mbcal.language.targets import target_points
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH, Dim, describe, fits, within

__all__ = ["build_model", "JOINT_KINDS"]

# Joint kind → the dimension of its variable.
JOINT_KINDS = {"revolute": ANGLE, "continuous": ANGLE, "prismatic": LENGTH}


def build_model(c: Compiler) -> Model:
    """Compile everything the first pass declared into a model.

    Parameters
    ----------
    c : Compiler
        The expression compiler, holding the namespace of the first pass.

    Returns
    -------
    Model
        Not yet checked at the nominal values (see :func:`mbcal.language.check.check`).

    Raises
    ------
    MdlError
        The first error, with its location.
    """
    unit_overrides: list[tuple[str, Dim, ast.Expr, str]] = []
    with recording_uses() as uses:
        model = _build_model(c, unit_overrides)
    if uses:
        params = tuple(
            dataclasses.replace(p, used_as=tuple(sorted(uses[p.index], key=repr)))
            if p.dim is None and p.index in uses
            else p
            for p in model.params
        )
        model = dataclasses.replace(model, params=params)
    _check_unit_overrides(model, unit_overrides)
    return model


def _check_unit_overrides(model: Model, unit_overrides: list[tuple[str, Dim, ast.Expr, str]]) -> None:
    """An ``override`` with a unit of a parameter declared without one: the unit must be of the
    dimension its places require, as ``--set`` and a file's known values are read
    (``ParamInfo.given_dim``) — known only once the whole model is compiled."""
    for name, dim, node, what in unit_overrides:
        given = model.param(name).given_dim
        if dim != (given or DIMENSIONLESS):
            used = f"used as {describe(given)}" if given is not None else "not used as one dimension: a plain number"
            raise UnitError(
                f"'{name}' is declared without a unit and {used}; {what} is {describe(dim)}",
                node.span,
                hint="write the value in a unit of that dimension, or as a plain number in SI units",
            )


def _build_model(c: Compiler, unit_overrides: list[tuple[str, Dim, ast.Expr, str]]) -> Model:
    names = c.names
    for decl in names.params.values():
        c.finish_param(decl)
    _apply_overrides(c, names, unit_overrides)
    frames = []
    for i, f in enumerate(names.frames):
        pose = c.pose(f.pose, f.scope) if f.pose is not None else None
        joint = _joint(c, names.joints[i]) if i in names.joints else None
        frames.append(FrameInfo(f.name, f.parent, pose, joint, f.keyword, f.span))
    points: list[PointInfo] = []
    cameras: list[CameraInfo] = []
    ranges: list[RangeInfo] = []
    shapes: list[ShapeInfo] = []
    shape_checker = ShapeChecker(c)
    shape_counter: dict[int, int] = {}
    targets: list[TargetInfo] = []
    for d in names.deferred:
        stmt = d.stmt
        if isinstance(stmt, ast.Point):
            assert stmt.value is not None
            node = c.compile(stmt.value, d.scope)
            c.expect(node, VECTOR, 3, LENGTH, f"point '{stmt.name}'", stmt.value.span)
            points.append(PointInfo(d.name, d.frame, node, stmt.span))
        elif isinstance(stmt, ast.Shape):
            n = shape_counter.get(d.frame, 0)
            while stmt.name is None and d.scope.join(f"shape{n}") in names.declared:
                n += 1  # an automatic name never takes one written in the frame (shape shape1 = ...)
            shape_counter[d.frame] = n + 1
            name = d.name or d.scope.join(f"shape{n}" if stmt.name is None else stmt.name)
            shapes.append(shape_checker.shape(stmt, d.scope, d.frame, name))
        elif isinstance(stmt, ast.Camera):
            cameras.append(camera(c, stmt, d.scope, d.frame, d.name))
        elif isinstance(stmt, ast.RangeSensor):
            ranges.append(range_sensor(c, stmt, d.scope, d.frame, d.name))
        elif isinstance(stmt, ast.Target):
            target_pts, target = target_points(c, stmt, d.scope, d.frame, d.name)
            points.extend(target_pts)
            targets.append(target)
    params = []
    for decl in sorted(names.params.values(), key=lambda d: d.index):
        assert decl.info is not None  # every parameter was finished above
        params.append(decl.info)
    return Model(
        path=names.path,
        params=tuple(params),
        frames=tuple(frames),
        points=tuple(points),
        cameras=tuple(cameras),
        ranges=tuple(ranges),
        shapes=tuple(shapes),
        measures=tuple(names.measures),
        measure_spans=tuple(names.measure_spans),
        targets=tuple(targets),
        templates=tuple(names.templates),
        files=tuple(dict.fromkeys(names.files)),
        data_files=tuple(
            dict.fromkeys(
                [*names.data_files, *(f for s in shapes if s.mesh is not None for f in (s.mesh.path, *s.mesh.buffers))]
            )
        ),
        warnings=tuple(names.warnings),
    )


def _apply_overrides(c: Compiler, names: Namespace, unit_overrides: list[tuple[str, Dim, ast.Expr, str]]) -> None:
    # An override that one in an including file replaces is checked as if it applied.
    for stmt, scope in names.shadowed:
        _override(c, names, stmt, scope, unit_overrides)
    for stmt, scope in names.overrides.values():
        decl, nominal, sigma = _override(c, names, stmt, scope, unit_overrides)
        assert decl.info is not None and stmt.value is not None
        decl.info = dataclasses.replace(
            decl.info,
            nominal=nominal,
            sigma=sigma,
            value_span=stmt.value.span,
            value_unit=literal_unit(stmt.value),
            editable=True,
            overridden=True,
        )


def _override(
    c: Compiler,
    names: Namespace,
    stmt: ast.Override,
    scope: Scope,
    unit_overrides: list[tuple[str, Dim, ast.Expr, str]],
) -> tuple[ParamDecl, float, float | None]:
    """An ``override`` statement checked: the parameter's declaration, its new nominal value and
    its prior σ (the statement's, else the declaration's)."""
    name = stmt.name
    decl = names.params.get(name)
    if decl is None:
        raise UndefinedNameError(
            f"'override' of an undeclared parameter '{name}'",
            stmt.name_span or stmt.span,
            hint=suggest(name, names.params),
        )
    info = decl.info
    assert info is not None and stmt.value is not None
    value = c.constant(stmt.value, scope, f"the override of '{name}'")
    if info.dim is not None and not fits(value.dim, info.dim):
        raise UnitError(f"'{name}' is {describe(info.dim)}, the override is {describe(value.dim)}", stmt.value.span)
    if info.dim is None and value.dim is not None:
        unit_overrides.append((name, value.dim, stmt.value, "the override"))
    if not math.isfinite(float(value.value)):
        raise DimensionError(f"the override of '{name}' is not a finite number", stmt.value.span)
    lo, hi = info.limit_lower, info.limit_upper
    if not within(float(value.value), -math.inf if lo is None else lo, math.inf if hi is None else hi):
        raise DimensionError(
            f"the override {written(float(value.value), stmt.value, info.dim)} of '{name}' lies outside its "
            f"limits {shown_limits(lo, hi, decl.stmt, info.dim)}",
            stmt.value.span,
        )
    sigma = info.sigma
    if stmt.sigma is not None:
        s = c.constant(stmt.sigma, scope, f"the sigma of the override of '{name}'")
        if info.dim is not None and not fits(s.dim, info.dim):
            raise UnitError(f"the sigma of '{name}' must be {describe(info.dim)}", stmt.sigma.span)
        if info.dim is None and s.dim is not None:
            unit_overrides.append((name, s.dim, stmt.sigma, "the override's sigma"))
        sigma = float(s.value)
        if not math.isfinite(sigma):
            raise DimensionError(f"the sigma of the override of '{name}' is not a finite number", stmt.sigma.span)
        if not sigma > 0:
            raise DimensionError(f"sigma must be positive, got {sigma:g}", stmt.sigma.span)
    return decl, float(value.value), sigma


def _joint(c: Compiler, d: Deferred) -> JointInfo:
    stmt = d.stmt
    assert isinstance(stmt, ast.Joint)
    if stmt.kind not in JOINT_KINDS:
        raise MdlError(
            f"unknown joint kind '{stmt.kind}' (revolute, continuous or prismatic)",
            stmt.span,
            hint=suggest(stmt.kind, JOINT_KINDS),
        )
    dim = JOINT_KINDS[stmt.kind]
    signature = [("axis", True), ("q", True), ("offset", False), ("lower", False), ("upper", False)]
    bound = bind(f"joint {stmt.kind}", signature, stmt.args, stmt.kwargs, stmt.span)
    axis = c.axis(bound["axis"], d.scope)
    q = c.arg(bound, "q", d.scope, dim=dim, what="the joint variable")
    offset = c.arg(bound, "offset", d.scope, dim=dim, what="the joint offset")
    limits = []
    for key in ("lower", "upper"):
        node = c.arg(bound, key, d.scope, dim=dim, what=f"the joint's {key} limit")
        if node is not None and not isinstance(node, Const):
            raise MdlError(f"the joint's {key} limit must be a constant", bound[key].span)
        if isinstance(node, Const) and not math.isfinite(float(node.value)):
            raise DimensionError(f"the joint's {key} limit is not a finite number", bound[key].span)
        limits.append(float(node.value) if isinstance(node, Const) else None)
    lo, hi = limits
    if lo is not None and hi is not None and not lo <= hi:
        shown = [math.degrees(v) if dim == ANGLE else v for v in (lo, hi)]
        unit = "deg" if dim == ANGLE else "m"
        raise MdlError(
            f"the joint's lower limit ({shown[0]:g} {unit}) is above its upper limit ({shown[1]:g} {unit})",
            bound["lower"].span,
            hint="swap them: lower = the smaller value",
        )
    assert q is not None
    kind = "revolute" if stmt.kind == "continuous" else stmt.kind
    return JointInfo(kind, axis, q, offset, limits[0], limits[1], stmt.span)
