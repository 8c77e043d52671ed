"""Syntax tree → checked :class:`~mbcal.language.model.Model`.

The checker runs in three passes:

1. :mod:`mbcal.language.expand` expands templates and includes and gives every declaration its
   full dotted name and scope (:mod:`mbcal.language.scope` says how names are looked up);
2. :mod:`mbcal.language.declarations` compiles every declaration — expressions through
   :mod:`mbcal.language.expressions`, which resolves names, checks kinds and units, types
   function calls with the catalogue (:mod:`mbcal.language.functions`) and folds constants;
3. :func:`check_at_nominal` checks sizes and poses at the nominal parameter values.

Everything a user can get wrong ends in a typed :class:`~mbcal.errors.MdlError` that points at
the offending text.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from mbcal.errors import DimensionError, SourceSpan
from mbcal.language import ast, ir
from mbcal.language.declarations import build_model
from mbcal.language.expand import expand
from mbcal.language.expressions import Compiler
from mbcal.language.functions import look_at_problem
from mbcal.language.graph import Node, Op
from mbcal.language.model import Model
from mbcal.language.shapes import check_shapes_at_nominal

__all__ = ["check", "check_at_nominal"]


def check(statements: Sequence[ast.Statement], path: str) -> Model:
    """Check parsed statements and build the :class:`Model`.

    Parameters
    ----------
    statements : sequence of ast.Statement
        The parsed model, includes resolved (:func:`mbcal.language.parse.parse_file`).
    path : str
        The model file, ``<string>`` for text.

    Returns
    -------
    Model
        The checked model.

    Raises
    ------
    MdlError
        The first error in the model, with its location.
    """
    model = build_model(Compiler(expand(statements, path)))
    check_at_nominal(model)
    return model


def check_at_nominal(
    model: Model, X: np.ndarray | None = None, where: str = "at the nominal values", *, finite: bool = True
) -> None:
    """Dimensions and focal lengths must be positive, and camera settings, joints, poses and
    points finite, at the nominal parameter values (or at ``X``, all parameter values; ``where``
    says which in the messages).  ``finite=False``: the signs only (sizes, focal lengths) — for
    the estimate of a fit, whose residuals were finite (the fit verdict's check, ~10× cheaper).

    Raises
    ------
    DimensionError
        At the first shape size, camera setting, joint, pose or point that is not.
    """
    X = model.nominal if X is None else np.asarray(X, dtype=float)
    memo: dict[int, object] = {}

    def value(node: Node) -> np.ndarray:
        with np.errstate(all="ignore"):
            return np.asarray(ir.evaluate(node, X, memo, np), dtype=float)

    check_shapes_at_nominal(model.shapes, value, where)
    for cam in model.cameras:
        for key, node in zip(("fx", "fy"), cam.intrinsics[:2]):
            v = float(value(node))
            if not (math.isfinite(v) and v > 0):
                raise DimensionError(
                    f"camera '{cam.name}': {key} must be positive, got {v:g} {where}", node.span or cam.span
                )
        if not finite:
            continue
        keys = ("cx", "cy", "skew", "k1", "k2", "p1", "p2", "k3")
        for key, node in zip(keys, (*cam.intrinsics[2:], *cam.distortion)):
            if not math.isfinite(float(value(node))):
                raise DimensionError(
                    f"camera '{cam.name}': {key} is not a finite number {where}", node.span or cam.span
                )

    def pose_error(what: str, pose: Node, span: SourceSpan | None) -> DimensionError:
        """The error of a pose that is not finite: a look_at in it that looks along its up, or
        from its target, names the cause."""
        for node in _nodes(pose):
            if isinstance(node, Op) and node.op == "look_at":
                problem = look_at_problem(*(value(a) for a in node.args))
                if problem is not None:
                    message, hint = problem
                    return DimensionError(
                        f"the pose of {what} is not finite {where}: {message}", node.span or span, hint
                    )
        return DimensionError(f"the pose of {what} is not finite {where} (a zero axis or quaternion?)", span)

    if not finite:
        return
    for frame in model.frames:
        joint = frame.joint
        if joint is not None:
            for what, part in (("axis", joint.axis), ("variable", joint.q), ("offset", joint.offset)):
                if part is not None and not np.all(np.isfinite(value(part))):
                    why = " (a zero axis?)" if what == "axis" else ""
                    raise DimensionError(
                        f"the {what} of the joint of '{frame.name}' is not finite {where}{why}",
                        part.span or joint.span,
                    )
        if frame.pose is not None and not np.all(np.isfinite(value(frame.pose))):
            raise pose_error(f"'{frame.name}'", frame.pose, frame.pose.span or frame.span)
    for shape in model.shapes:
        if shape.pose is not None and not np.all(np.isfinite(value(shape.pose))):
            raise pose_error(f"shape '{shape.name}'", shape.pose, shape.pose.span or shape.span)
    for point in model.points:
        if not np.all(np.isfinite(value(point.position))):
            raise DimensionError(f"point '{point.name}' is not finite {where}", point.span)


def _nodes(root: Node) -> list[Node]:
    """Every node of a graph, each once (without recursion: a graph may be deep)."""
    seen: dict[int, Node] = {}
    stack = [root]
    while stack:
        node = stack.pop()
        if id(node) not in seen:
            seen[id(node)] = node
            if isinstance(node, Op):
                stack.extend(node.args)
    return list(seen.values())
