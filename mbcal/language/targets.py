"""Calibration targets: a frame carrying named points in its xy-plane.

* ``chessboard(rows, cols, square)``: the inner corners ``T.r0c0`` … of a chessboard, row by
  row — the order of OpenCV's ``findChessboardCorners`` for a pattern size ``(cols, rows)``;
  corner (r, c) is at ``(c·square, r·square, 0)``.
* ``grid(rows, cols, dx, dy = dx)``: the same with separate spacings.
* ``squares(rows, cols, size, pitch)``: separated black squares (Zhang's pattern); square (r, c)
  has its corner 0 at ``(c·pitch, r·pitch, 0)`` and corners ``T.r{r}c{c}k{k}``, k = 0..3 at
  offsets (0, 0), (size, 0), (size, size), (0, size).
* ``points(file, scale = 1 m, columns = 2)``: points read from a text file of numbers (``#``
  comments allowed), taken ``columns`` (2: x y, z = 0; or 3) at a time in file order, times
  ``scale``; named ``T.p0``, ``T.p1``, …  The file is relative to the model file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mbcal.errors import DimensionError, MdlError, MdlTypeError, UndefinedNameError, suggest
from mbcal.language import ast, files
from mbcal.language.arguments import bind
from mbcal.language.expressions import Compiler
from mbcal.language.graph import SCALAR, VECTOR, Const, Node
from mbcal.language.ir import make_op
from mbcal.language.model import PointInfo, TargetInfo
from mbcal.language.scope import Scope
from mbcal.units import DIMENSIONLESS, LENGTH

__all__ = ["TARGET_KINDS", "SQUARE_CORNERS", "MAX_TARGET_POINTS", "corner_name", "target_points"]

TARGET_KINDS = {
    "chessboard": [("rows", True), ("cols", True), ("square", True)],
    "grid": [("rows", True), ("cols", True), ("dx", True), ("dy", False)],
    "squares": [("rows", True), ("cols", True), ("size", True), ("pitch", True)],
    "points": [("file", True), ("scale", False), ("columns", False)],
}
SQUARE_CORNERS = ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0))
MAX_TARGET_POINTS = 100_000


def corner_name(target: str, row: int, col: int) -> str:
    """The point name of corner (row, col) of a target."""
    return f"{target}.r{row}c{col}"


def target_points(
    checker: Compiler, stmt: ast.Target, scope: Scope, frame: int, name: str
) -> tuple[list[PointInfo], TargetInfo]:
    """Compile a ``target`` statement into its named points and its description.

    Parameters
    ----------
    checker : Compiler
        The model's expression compiler.
    stmt : ast.Target
        The statement.
    scope : Scope
        Where it stands.
    frame : int
        The target's own frame.
    name : str
        Its full name (the points are ``name.r0c0``, ...).

    Returns
    -------
    points : list of PointInfo
        The target's points, in detection order.
    info : TargetInfo
        Its kind and layout.
    """
    points = _points(checker, stmt, scope, frame, name)
    rows = cols = 0
    ratio = 0.0
    if stmt.kind != "points":
        bound = bind(stmt.kind, TARGET_KINDS[stmt.kind], stmt.args, stmt.kwargs, stmt.span)
        counts = []
        for key in ("rows", "cols"):
            node = checker.compile(bound[key], scope)
            assert isinstance(node, Const)  # _points() refused anything else
            counts.append(int(float(node.value)))
        rows, cols = counts
        if stmt.kind == "squares":
            size = checker.compile(bound["size"], scope)
            pitch = checker.compile(bound["pitch"], scope)
            if isinstance(size, Const) and isinstance(pitch, Const):
                ratio = float(size.value) / float(pitch.value)
    info = TargetInfo(name, stmt.kind, frame, rows, cols, tuple(p.name for p in points), ratio, stmt.span)
    return points, info


def _points(checker: Compiler, stmt: ast.Target, scope: Scope, frame: int, name: str) -> list[PointInfo]:
    if stmt.kind not in TARGET_KINDS:
        raise UndefinedNameError(
            f"unknown target '{stmt.kind}' (one of {', '.join(TARGET_KINDS)})",
            stmt.kind_span or stmt.span,
            hint=suggest(stmt.kind, TARGET_KINDS),
        )
    bound = bind(stmt.kind, TARGET_KINDS[stmt.kind], stmt.args, stmt.kwargs, stmt.span)
    if stmt.kind == "points":
        return _file_points(checker, stmt, bound, scope, frame, name)
    counts = []
    for key in ("rows", "cols"):
        node = checker.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"'{key}'")
        if not isinstance(node, Const) or float(node.value) != round(float(node.value)) or float(node.value) < 1:
            raise DimensionError(f"'{key}' must be a positive whole number", bound[key].span)
        counts.append(int(node.value))
    rows, cols = counts
    if rows * cols > MAX_TARGET_POINTS:
        raise DimensionError(f"a target has at most {MAX_TARGET_POINTS} points, got {rows * cols}", stmt.span)
    if stmt.kind == "squares":
        return _square_points(checker, stmt, bound, scope, frame, name, rows, cols)
    if stmt.kind == "chessboard":
        dx = dy = checker.arg(bound, "square", scope, dim=LENGTH, what="the square size")
    else:
        dx = checker.arg(bound, "dx", scope, dim=LENGTH, what="dx")
        dy = checker.arg(bound, "dy", scope, dim=LENGTH, what="dy") if "dy" in bound else dx
    assert dx is not None and dy is not None
    for node, key in ((dx, "square" if stmt.kind == "chessboard" else "dx"), (dy, "dy")):
        if isinstance(node, Const) and not float(node.value) > 0:
            raise DimensionError("the grid spacing must be positive", bound.get(key, stmt).span)
    zero = Const(kind=SCALAR, dim=None, value=np.asarray(0.0))
    points = []
    for r in range(rows):
        for c in range(cols):
            x = make_op("mul", [Const(kind=SCALAR, dim=None, value=np.asarray(float(c))), dx], SCALAR, LENGTH)
            y = make_op("mul", [Const(kind=SCALAR, dim=None, value=np.asarray(float(r))), dy], SCALAR, LENGTH)
            pos = make_op("vec", [x, y, zero], VECTOR, LENGTH, 3, stmt.span)
            points.append(PointInfo(corner_name(name, r, c), frame, pos, stmt.span))
    return points


def _scaled(value: float, length: Node) -> Node:
    return make_op("mul", [Const(kind=SCALAR, dim=None, value=np.asarray(float(value))), length], SCALAR, LENGTH)


def _square_points(
    checker: Compiler,
    stmt: ast.Target,
    bound: dict[str, ast.Expr],
    scope: Scope,
    frame: int,
    name: str,
    rows: int,
    cols: int,
) -> list[PointInfo]:
    size = checker.arg(bound, "size", scope, dim=LENGTH, what="the square size")
    pitch = checker.arg(bound, "pitch", scope, dim=LENGTH, what="the pitch (distance between squares)")
    assert size is not None and pitch is not None  # required by TARGET_KINDS
    for node, key in ((size, "size"), (pitch, "pitch")):
        if isinstance(node, Const) and not float(node.value) > 0:
            raise DimensionError(f"'{key}' must be positive", bound[key].span)
    if isinstance(size, Const) and isinstance(pitch, Const) and not float(size.value) < float(pitch.value):
        raise DimensionError("the squares must be smaller than their pitch (or they touch)", bound["size"].span)
    zero = Const(kind=SCALAR, dim=None, value=np.asarray(0.0))
    points = []
    for r in range(rows):
        for c in range(cols):
            for k, (a, b) in enumerate(SQUARE_CORNERS):
                x = make_op("add", [_scaled(c, pitch), _scaled(a, size)], SCALAR, LENGTH)
                y = make_op("add", [_scaled(r, pitch), _scaled(b, size)], SCALAR, LENGTH)
                pos = make_op("vec", [x, y, zero], VECTOR, LENGTH, 3, stmt.span)
                points.append(PointInfo(f"{name}.r{r}c{c}k{k}", frame, pos, stmt.span))
    return points


def _file_points(
    checker: Compiler, stmt: ast.Target, bound: dict[str, ast.Expr], scope: Scope, frame: int, name: str
) -> list[PointInfo]:
    expr = bound["file"]
    if not isinstance(expr, ast.String):
        raise MdlTypeError('points() needs a file name in quotes: points("corners.txt")', expr.span)
    base = Path(expr.span.path).resolve().parent if expr.span.path != "<string>" else Path.cwd()
    path = base / expr.value
    scale = checker.arg(bound, "scale", scope, dim=LENGTH, what="the scale") if "scale" in bound else None
    columns = 2
    if "columns" in bound:
        node = checker.arg(bound, "columns", scope, dim=DIMENSIONLESS, what="'columns'")
        if not isinstance(node, Const) or float(node.value) not in (2.0, 3.0):
            raise DimensionError("'columns' is 2 (x y) or 3 (x y z)", bound["columns"].span)
        columns = int(node.value)
    checker.names.data_files.append(str(path.resolve()))
    try:
        text = files.read_bytes(path).decode("utf-8")
    except FileNotFoundError:
        raise MdlError(f"point file not found: {path}", expr.span) from None
    except (OSError, UnicodeDecodeError) as err:
        raise MdlError(f"cannot read point file {path}: {err}", expr.span) from None
    values = []
    for line_no, line in enumerate(text.splitlines(), 1):
        for item in line.split("#", 1)[0].replace(",", " ").split():
            try:
                v = float(item)
            except ValueError:
                raise MdlError(f"{path}:{line_no}: not a number: {item!r}", expr.span) from None
            if not np.isfinite(v):
                raise MdlError(f"{path}:{line_no}: not a finite number: {item!r}", expr.span)
            values.append(v)
    if not values or len(values) % columns:
        raise MdlError(f"{path} holds {len(values)} numbers: not a whole number of {columns}-D points", expr.span)
    if len(values) // columns > MAX_TARGET_POINTS:
        raise DimensionError(f"a target has at most {MAX_TARGET_POINTS} points", expr.span)
    coords = np.asarray(values).reshape(-1, columns)
    points = []
    for k, row in enumerate(coords):
        xyz = list(row) + [0.0] * (3 - columns)
        items = [
            _scaled(v, scale) if scale is not None else Const(kind=SCALAR, dim=LENGTH, value=np.asarray(v)) for v in xyz
        ]
        pos = make_op("vec", items, VECTOR, LENGTH, 3, stmt.span)
        points.append(PointInfo(f"{name}.p{k}", frame, pos, stmt.span))
    return points
