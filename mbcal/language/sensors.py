"""Sensor statements → :class:`CameraInfo` and :class:`RangeInfo`.

``camera NAME(width = ..., height = ..., f = ...)`` is a pinhole camera with OpenCV's axes and
distortion model; ``range NAME(direction = ... | directions = [...] | fov = ..., rays = ...)`` a
range sensor casting fixed rays from its frame's origin; with ``width``, ``height`` and a focal
length it is a depth camera (pinhole intrinsics, depth scale, valid range).
"""

from __future__ import annotations

import math

import numpy as np

from mbcal.errors import ArgumentError, DimensionError, MdlError, MdlTypeError, SourceSpan
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.expressions import Compiler
from mbcal.language.graph import SCALAR, VECTOR, Const, Node
from mbcal.language.model import CameraInfo, RangeInfo
from mbcal.language.scope import Scope
from mbcal.units import ANGLE, DIMENSIONLESS, LENGTH

__all__ = ["camera", "range_sensor"]

MAX_PIXELS = 16384  # the largest image side, of cameras and depth cameras

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
        # At most MAX_PIXELS a side, as a depth camera: OpenGL's renderbuffers (mbcal render, the
        # overlays) go no larger, and a larger camera passed 'mbcal check' to fail in the renderer.
        value = node.value if isinstance(node, Const) and node.kind == SCALAR else None
        v = math.nan if value is None else float(value)
        if not (1 <= v <= MAX_PIXELS and v == round(v)):
            got = " (a constant)" if value is None else f", got {v:g}"
            raise DimensionError(
                f"the camera's {key} must be a whole number of pixels in 1..{MAX_PIXELS}{got}", bound[key].span
            )
        size.append(int(v))
    _check_focal_lengths(f"camera '{stmt.name}'", bound, stmt.span)
    if "f" in bound:
        fx = fy = c.arg(bound, "f", scope, dim=DIMENSIONLESS, what="the focal length f (pixels)")
    else:
        fx = c.arg(bound, "fx", scope, dim=DIMENSIONLESS, what="fx (pixels)")
        fy = c.arg(bound, "fy", scope, dim=DIMENSIONLESS, what="fy (pixels)")
    assert fx is not None and fy is not None

    def pixel(key: str, default: float) -> Node:
        node = c.arg(bound, key, scope, dim=DIMENSIONLESS, what=f"'{key}'")
        return node if node is not None else Const(kind=SCALAR, dim=None, value=np.asarray(default))

    cx = pixel("cx", (size[0] - 1) / 2.0)
    cy = pixel("cy", (size[1] - 1) / 2.0)
    skew = pixel("skew", 0.0)
    k1, k2, p1, p2, k3 = (pixel(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3"))
    return CameraInfo(name, frame, size[0], size[1], (fx, fy, cx, cy, skew), (k1, k2, p1, p2, k3), stmt.span)


def _check_focal_lengths(what: str, bound: dict[str, ast.Expr], span: SourceSpan | None) -> None:
    """``f = F`` or ``fx = FX, fy = FY``: one focal length for both axes or one for each, never
    both forms and never one of fx, fy alone (``what`` names the camera in messages)."""
    given = [k for k in ("fx", "fy") if k in bound]
    if "f" in bound and given:
        raise ArgumentError(
            f"{what} takes f = ... or fx = ..., fy = ..., not both",
            bound[given[0]].span,
            hint="f is the focal length of both axes: drop it, or drop fx and fy",
        )
    if "f" not in bound and not given:
        raise ArgumentError(f"{what} needs a focal length: f = ... or fx = ..., fy = ...", span)
    if len(given) == 1:
        missing = "fy" if given[0] == "fx" else "fx"
        raise ArgumentError(
            f"{what} has {given[0]} but no {missing}: give both (or f = ... for both)", bound[given[0]].span
        )


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
    keys += [(k, False) for k in DEPTH_SETTINGS]
    bound = bind(f"range {stmt.name}", keys, (), stmt.kwargs, stmt.span)
    if "width" in bound or "height" in bound:
        return _depth_camera(c, stmt, bound, scope, frame, name)
    for key in DEPTH_SETTINGS:
        if key in bound:
            raise ArgumentError(
                f"'{key}' is a depth camera's setting: give the image size too (width = ..., height = ...)",
                bound[key].span,
            )
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
        dirs = _fan(float(fov.value[0]), float(fov.value[1]), cols, rows, bound["fov"].span)
    max_range = 1e3
    if "max" in bound:
        node = c.arg(bound, "max", scope, dim=LENGTH, what="the maximum range")
        if not isinstance(node, Const) or not 0 < float(node.value) < math.inf:
            raise DimensionError("the maximum range must be a positive finite constant", bound["max"].span)
        max_range = float(node.value)
    return RangeInfo(name, frame, dirs, max_range, stmt.span)


def _fan(h: float, v: float, cols: int, rows: int, span: SourceSpan | None) -> np.ndarray:
    """The unit rays of ``fov = (h, v), rays = (cols, rows)`` (angles in radians), row by row.

    A single row sweeps its rays by angle about the frame's y axis, (sin a, 0, cos a), a single
    column about its x axis, (0, sin a, cos a): either may span up to a full turn, and a full
    turn spaces its rays 360°/n apart from straight back (−180°), without repeating the first.
    A grid (more than one column and row) places its rays like a camera's pixels, at
    (tan a, tan b, 1): each field of view must be below 180°.  Below 180° a single row or column
    gets the same rays either way.
    """
    turn = 2 * math.pi
    if cols > 1 and rows > 1:
        for angle, which in ((h, "horizontal"), (v, "vertical")):
            if not abs(angle) < math.pi:
                raise DimensionError(
                    f"a grid of rays needs a {which} field of view below 180 deg, got {math.degrees(angle):g} deg",
                    span,
                    hint="only a single row or column of rays (rays = (n, 1) or (1, n)) may span up to 360 deg",
                )
        hh, vv = np.meshgrid(np.tan(np.linspace(-h / 2, h / 2, cols)), np.tan(np.linspace(-v / 2, v / 2, rows)))
        d = np.stack([hh.ravel(), vv.ravel(), np.ones(hh.size)], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)
    n, angle = (cols, h) if cols > 1 else (rows, v)
    if n == 1:
        return np.array([[0.0, 0.0, 1.0]])
    full = math.isclose(abs(angle), turn, rel_tol=1e-12)
    if abs(angle) > turn and not full:
        which = "row" if cols > 1 else "column"
        raise DimensionError(f"a single {which} of rays spans at most 360 deg, got {math.degrees(angle):g} deg", span)
    a = np.linspace(-angle / 2, angle / 2, n, endpoint=not full)
    s, c = np.sin(a), np.cos(a)
    zero = np.zeros(n)
    return np.stack([s, zero, c] if cols > 1 else [zero, s, c], axis=1)


DEPTH_SETTINGS = ("width", "height", "f", "fx", "fy", "cx", "cy", "scale", "min")


def _constant(c: Compiler, bound: dict, key: str, scope: Scope, dim, what: str) -> float | None:
    node = c.arg(bound, key, scope, dim=dim, what=what)
    if node is None:
        return None
    if not isinstance(node, Const) or not math.isfinite(float(node.value)):
        raise MdlError(f"{what} must be a constant", bound[key].span)
    return float(node.value)


def _depth_camera(c: Compiler, stmt: ast.RangeSensor, bound: dict, scope: Scope, frame: int, name: str) -> RangeInfo:
    """A depth camera: ``range NAME(width = W, height = H, f = F | fx = .., fy = .., [cx, cy],
    [scale = 1 mm], [min = ...], [max = ...])`` — pinhole intrinsics in pixels (OpenCV's axes),
    the depth unit of its images and the valid range; one ray through each pixel centre."""
    for key in ("direction", "directions", "fov", "rays"):
        if key in bound:
            raise ArgumentError(
                f"a depth camera's rays come from its intrinsics: drop '{key}' (or drop width and height)",
                bound[key].span,
            )
    size = []
    for key in ("width", "height"):
        if key not in bound:
            raise ArgumentError(f"depth camera '{stmt.name}' needs '{key}' (image size in pixels)", stmt.span)
        v = _constant(c, bound, key, scope, DIMENSIONLESS, f"the depth camera's {key}")
        if v is None or v != round(v) or not 1 <= v <= MAX_PIXELS:
            raise DimensionError(
                f"the depth camera's {key} must be a whole number of pixels in 1..{MAX_PIXELS}", bound[key].span
            )
        size.append(int(v))
    if size[0] * size[1] > 4_000_000:
        raise DimensionError("a depth camera may have at most 4 million pixels", bound["width"].span)
    _check_focal_lengths(f"depth camera '{stmt.name}'", bound, stmt.span)
    focal = {}
    for key in ("f",) if "f" in bound else ("fx", "fy"):
        v = _constant(
            c, bound, key, scope, DIMENSIONLESS, "the focal length f (pixels)" if key == "f" else f"{key} (pixels)"
        )
        assert v is not None
        if not v > 0:
            raise DimensionError(f"the focal length {key} must be positive, got {v:g}", bound[key].span)
        focal[key] = v
    fx, fy = (focal["f"], focal["f"]) if "f" in focal else (focal["fx"], focal["fy"])
    cx = _constant(c, bound, "cx", scope, DIMENSIONLESS, "cx (pixels)")
    cy = _constant(c, bound, "cy", scope, DIMENSIONLESS, "cy (pixels)")
    cx = (size[0] - 1) / 2.0 if cx is None else cx
    cy = (size[1] - 1) / 2.0 if cy is None else cy
    scale = _constant(c, bound, "scale", scope, LENGTH, "the depth scale (length per count)")
    scale = 1e-3 if scale is None else scale
    if not scale > 0:
        raise DimensionError("the depth scale must be positive (e.g. scale = 1 mm)", bound["scale"].span)
    lo = _constant(c, bound, "min", scope, LENGTH, "the minimum range") or 0.0
    hi = _constant(c, bound, "max", scope, LENGTH, "the maximum range")
    hi = 10.0 if hi is None else hi
    if not 0 <= lo < hi:
        raise DimensionError(
            "the valid range needs 0 <= min < max", (bound.get("min") or bound.get("max") or stmt).span
        )
    u, v = np.meshgrid(np.arange(size[0], dtype=float), np.arange(size[1], dtype=float))
    d = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], axis=1)
    dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
    return RangeInfo(name, frame, dirs, hi, stmt.span, (fx, fy, cx, cy), size[0], size[1], float(scale), float(lo))
