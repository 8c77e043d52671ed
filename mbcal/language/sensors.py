"""Sensor statements → :class:`CameraInfo` and :class:`RangeInfo`.

``camera NAME(width = ..., height = ..., f = ...)`` is a pinhole camera with OpenCV's axes and
distortion model; ``range NAME(direction = ... | directions = [...] | fov = ..., rays = ...)`` a
range sensor casting fixed rays from its frame's origin.
"""

from __future__ import annotations

import math

import numpy as np

from mbcal.errors import ArgumentError, DimensionError, MdlError, MdlTypeError
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.expressions import Compiler
from mbcal.language.graph import SCALAR, VECTOR, Const, Node
from mbcal.language.model import CameraInfo, RangeInfo
from mbcal.language.scope import Scope
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH

__all__ = ["camera", "range_sensor"]

CAMERA_SETTINGS = ("width", "height", "f", "fx", "fy", "cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")


def camera(c: Compiler, stmt: ast.Camera, scope: Scope, frame: int, name: str) -> CameraInfo:
    """Compile a ``camera`` statement.

    Parameters
    ----------
    c : Compiler
        The model's expression compiler.
    stmt : ast.Camera
        The statement.
    scope : Scope
        Where it stands.
    frame : int
        The camera's own frame.
    name : str
        Its full name.

    Returns
    -------
    CameraInfo
        Image size, intrinsics (fx, fy, cx, cy, skew) and distortion (k1, k2, p1, p2, k3).
    """
    if stmt.args:
        raise ArgumentError(
            "camera settings are named: camera NAME(width = ..., height = ..., f = ...)", stmt.args[0].span
        )
    bound = bind(f"camera {stmt.name}", [(k, False) for k in CAMERA_SETTINGS], (), stmt.kwargs, stmt.span)
    for required in ("width", "height"):
        if required not in bound:
            raise ArgumentError(f"camera '{stmt.name}' needs '{required}' (image size in pixels)", stmt.span)
    size = []
    for key in ("width", "height"):
        node = c.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"the camera's {key}")
        if not isinstance(node, Const) or float(node.value) != round(float(node.value)) or node.value <= 0:
            raise DimensionError(f"the camera's {key} must be a positive whole number of pixels", bound[key].span)
        size.append(int(node.value))
    f = c.arg(bound, "f", scope, dim=DIMENSIONLESS, what="the focal length f (pixels)")
    fx = c.arg(bound, "fx", scope, dim=DIMENSIONLESS, what="fx (pixels)") or f
    fy = c.arg(bound, "fy", scope, dim=DIMENSIONLESS, what="fy (pixels)") or f
    if fx is None or fy is None:
        raise ArgumentError(f"camera '{stmt.name}' needs a focal length: f = ... or fx = ..., fy = ...", stmt.span)

    def pixel(key: str, default: float) -> Node:
        node = c.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"'{key}'")
        return node if node is not None else Const(kind=SCALAR, dim=None, value=np.asarray(default))

    cx = pixel("cx", (size[0] - 1) / 2.0)
    cy = pixel("cy", (size[1] - 1) / 2.0)
    skew = pixel("skew", 0.0)
    k1, k2, p1, p2, k3 = (pixel(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3"))
    return CameraInfo(name, frame, size[0], size[1], (fx, fy, cx, cy, skew), (k1, k2, p1, p2, k3), stmt.span)


def _const_vectors(c: Compiler, expr: ast.Expr, scope: Scope, what: str) -> np.ndarray:
    items = expr.items if isinstance(expr, ast.List) else (expr,)
    out = []
    for item in items:
        node = c.compile(item, scope)
        if not isinstance(node, Const) or node.kind != VECTOR or node.size != 3:
            raise MdlTypeError(f"{what} must be constant 3-vectors", item.span)
        n = float(np.linalg.norm(node.value))
        if not n > 0 or not math.isfinite(n):
            raise DimensionError("a direction must not be the zero vector", item.span)
        out.append(node.value / n)
    if not out:
        raise ArgumentError(f"{what}: the list is empty", expr.span)
    return np.asarray(out, dtype=float)


def range_sensor(c: Compiler, stmt: ast.RangeSensor, scope: Scope, frame: int, name: str) -> RangeInfo:
    """Compile a ``range`` statement (parameters as :func:`camera`): unit ray directions in the
    sensor frame and the maximum range."""
    if stmt.args:
        raise ArgumentError("range sensor settings are named: range NAME(direction = (0, 0, 1))", stmt.args[0].span)
    keys = [("direction", False), ("directions", False), ("fov", False), ("rays", False), ("max", False)]
    bound = bind(f"range {stmt.name}", keys, (), stmt.kwargs, stmt.span)
    given = [k for k in ("direction", "directions", "fov") if k in bound]
    if len(given) != 1:
        raise ArgumentError(
            f"range sensor '{stmt.name}' needs exactly one of direction = ..., directions = [...] "
            "or fov = (h, v), rays = (columns, rows)",
            stmt.span,
        )
    if "direction" in bound:
        dirs = _const_vectors(c, bound["direction"], scope, "a direction")
        if len(dirs) != 1:
            raise ArgumentError("use 'directions = [...]' for several rays", bound["direction"].span)
    elif "directions" in bound:
        if not isinstance(bound["directions"], ast.List):
            raise MdlTypeError("'directions' takes a list: [(x, y, z), ...]", bound["directions"].span)
        dirs = _const_vectors(c, bound["directions"], scope, "each direction")
    else:
        fov = c.arg(bound, "fov", scope, kind=VECTOR, size=2, dim=ANGLE, what="fov (horizontal, vertical)")
        if "rays" not in bound:
            raise ArgumentError("a field of view needs rays = (columns, rows)", stmt.span)
        rays = c.arg(bound, "rays", scope, kind=VECTOR, size=2, dim=DIMENSIONLESS, what="rays (columns, rows)")
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
        node = c.arg(bound, "max", scope, dim=LENGTH, what="the maximum range")
        if not isinstance(node, Const) or not float(node.value) > 0:
            raise DimensionError("the maximum range must be a positive constant", bound["max"].span)
        max_range = float(node.value)
    return RangeInfo(name, frame, dirs, max_range, stmt.span)
