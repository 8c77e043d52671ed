"""Shape statements → :class:`ShapeInfo`, and the checks of their sizes at the nominal values.

``shape [name =] kind(dimensions...) at pose`` attaches a primitive (see
:mod:`mbcal.geometry.shapes`, the one table of shape kinds) or a mesh file to the enclosing frame.  All of the
checker's shape handling is here, in :class:`ShapeChecker` and :func:`check_shapes_at_nominal`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mbcal.errors import DimensionError, MdlTypeError, UndefinedNameError, UnitError, suggest
from mbcal.geometry.shapes import get_shape, shape_kinds
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.expressions import Compiler
from mbcal.language.graph import SCALAR, VECTOR, Const, Node, describe_kind, note_use
from mbcal.language.ir import make_op
from mbcal.language.meshes import load_mesh
from mbcal.language.model import MeshData, ShapeInfo
from mbcal.language.scope import Scope
from mbcal.units import DIMENSIONLESS, describe, fits

__all__ = ["ShapeChecker", "check_shapes_at_nominal"]


class ShapeChecker:
    """Compiles the shape statements of one model.

    Parameters
    ----------
    compiler : Compiler
        The model's expression compiler.
    """

    def __init__(self, compiler: Compiler):
        self.compiler = compiler
        self.mesh_cache: dict[str, MeshData] = {}

    def shape(self, stmt: ast.Shape, scope: Scope, frame: int, name: str) -> ShapeInfo:
        """Compile a ``shape`` statement (``name`` is its full name, given or generated)."""
        kind = stmt.kind
        kinds = shape_kinds()
        if kind not in kinds:
            raise UndefinedNameError(
                f"unknown shape '{kind}' (one of {', '.join(kinds)})",
                stmt.kind_span or stmt.span,
                hint=suggest(kind, kinds),
            )
        info = kinds[kind]
        pose = self.compiler.pose(stmt.pose, scope) if stmt.pose is not None else None
        mesh = None
        if info.from_file:
            bound = bind(kind, [("file", True), ("scale", False)], stmt.args, stmt.kwargs, stmt.span)
            mesh = self._mesh(bound["file"])
            scale_expr = bound.get("scale")
            if scale_expr is None:
                one = Const(kind=SCALAR, dim=None, value=np.asarray(1.0), span=stmt.span)
                dims: tuple[Node, ...] = (one, one, one)
            else:
                scale = self.compiler.compile(scale_expr, scope)
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
                    raise MdlTypeError(
                        f"a mesh scale is a number or a 3-vector, got {describe_kind(scale)}", scale_expr.span
                    )
                if not fits(scale.dim, DIMENSIONLESS):
                    raise UnitError(f"a mesh scale is a plain number, got {describe(scale.dim)}", scale_expr.span)
                note_use(scale, DIMENSIONLESS)
            return ShapeInfo(name, frame, kind, dims, pose, mesh, stmt.span)
        if info.sized is not None and (stmt.args or stmt.kwargs):
            kind, info = info.sized, kinds[info.sized]  # plane(sx, sy) is a rectangle
        signature = [(n, True) for n in info.dims]
        bound = bind(stmt.kind, signature, stmt.args, stmt.kwargs, stmt.span)
        nodes = []
        for n in info.dims:
            node = self.compiler.arg(bound, n, scope, dim=info.dim, what=f"{stmt.kind}() argument '{n}'")
            assert node is not None
            nodes.append(node)
        return ShapeInfo(name, frame, kind, tuple(nodes), pose, None, stmt.span)

    def _mesh(self, expr: ast.Expr) -> MeshData:
        # One read per file and check, however many shapes (or template instances) use it.
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


def check_shapes_at_nominal(
    shapes: Sequence[ShapeInfo], value: Callable[[Node], np.ndarray], where: str = "at the nominal values"
) -> None:
    """Shape dimensions and mesh scales must be positive at the nominal parameter values.

    Parameters
    ----------
    shapes : sequence of ShapeInfo
        The model's shapes.
    value : callable
        A node's value at the nominal parameter values.

    Raises
    ------
    DimensionError
        At the first shape whose dimensions its kind's rule refuses (not positive; a tube whose
        inner radius is not smaller).
    """
    for shape in shapes:
        values = [float(value(node)) for node in shape.dims]
        bad = get_shape(shape.kind).invalid(values)
        if bad is not None:
            index, message = bad
            message = message.replace("at the nominal values", where)
            raise DimensionError(message, shape.dims[index].span or shape.span)
