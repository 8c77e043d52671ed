"""Calibration targets: a frame carrying a regular grid of named points.

``target board = chessboard(rows = 6, cols = 9, square = 25 mm)`` declares the frame
``board`` and its inner corners ``board.r0c0`` … ``board.r5c8``, row by row — the order in
which OpenCV's ``findChessboardCorners`` reports them for a pattern size ``(cols, rows)``.
The grid lies in the target's xy-plane, starting at its origin: corner (r, c) is at
``(c·square, r·square, 0)``.  ``grid(rows, cols, dx, dy)`` is the same with separate spacings.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from mbcal.errors import DimensionError, UndefinedNameError, suggest
from mbcal.language import ast
from mbcal.language.ir import SCALAR, VECTOR, Const, make_op
from mbcal.language.model import PointInfo
from mbcal.units import DIMENSIONLESS, LENGTH

if TYPE_CHECKING:
    from mbcal.language.check import _Checker, _Scope

TARGET_KINDS = {
    "chessboard": [("rows", True), ("cols", True), ("square", True)],
    "grid": [("rows", True), ("cols", True), ("dx", True), ("dy", False)],
}
MAX_TARGET_POINTS = 100_000


def corner_name(target: str, row: int, col: int) -> str:
    """The point name of corner (row, col) of a target."""
    return f"{target}.r{row}c{col}"


def target_points(checker: _Checker, stmt: ast.Target, scope: _Scope, frame: int, name: str) -> list[PointInfo]:
    """Compile a ``target`` statement into its named points."""
    from mbcal.language.check import _bind

    if stmt.kind not in TARGET_KINDS:
        raise UndefinedNameError(
            f"unknown target '{stmt.kind}' (one of {', '.join(TARGET_KINDS)})",
            stmt.kind_span or stmt.span,
            hint=suggest(stmt.kind, TARGET_KINDS),
        )
    bound = _bind(stmt.kind, TARGET_KINDS[stmt.kind], stmt.args, stmt.kwargs, stmt.span)
    counts = []
    for key in ("rows", "cols"):
        node = checker.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"'{key}'")
        if not isinstance(node, Const) or float(node.value) != round(float(node.value)) or float(node.value) < 1:
            raise DimensionError(f"'{key}' must be a positive whole number", bound[key].span)
        counts.append(int(node.value))
    rows, cols = counts
    if rows * cols > MAX_TARGET_POINTS:
        raise DimensionError(f"a target has at most {MAX_TARGET_POINTS} points, got {rows * cols}", stmt.span)
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
