"""The resolved, typed expression graph that the modeler evaluates.

The checker turns every expression of a model into a small graph of :class:`Node` objects:
constants, parameter references and operations.  Names are resolved (a ``let`` or template
argument used twice is one shared node, evaluated once), every node knows its kind (scalar,
vector, transform) and its dimension, and everything that does not depend on a parameter is
folded to a numpy constant when the model is loaded.  Evaluation walks the graph with JAX —
mbcal never hands model text to Python's ``eval``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal import geometry as geo
from mbcal.errors import SourceSpan
from mbcal.units import Dim

__all__ = ["Node", "Const", "ParamRef", "Op", "SCALAR", "VECTOR", "TRANSFORM", "OPS", "make_op", "evaluate"]

SCALAR = "scalar"
VECTOR = "vector"
TRANSFORM = "transform"


@dataclass(eq=False)
class Node:
    """One node of the expression graph.

    Attributes
    ----------
    kind : str
        ``scalar``, ``vector`` or ``transform``.
    dim : Dim or None
        Physical dimension (None: a unitless literal that adapts to its use).
    size : int
        Number of components of a vector (0 otherwise).
    span : SourceSpan or None
        Where the expression stands in the source.
    """

    kind: str
    dim: Dim | None
    size: int = 0
    span: SourceSpan | None = field(default=None, repr=False)

    @property
    def is_constant(self) -> bool:
        return isinstance(self, Const)


@dataclass(eq=False)
class Const(Node):
    """A value known when the model is loaded (numpy)."""

    value: Any = None


@dataclass(eq=False)
class ParamRef(Node):
    """The value of parameter ``name`` (position ``index`` in the parameter vector)."""

    index: int = -1
    name: str = ""


@dataclass(eq=False)
class Op(Node):
    """``OPS[op](xp, *args)``."""

    op: str = ""
    args: tuple[Node, ...] = ()


def _vec(xp, *items):
    return xp.stack([xp.asarray(i, dtype=float) for i in items])


def _mul(xp, a, b):
    return a * b


def _safe_norm(xp, v):
    return xp.sqrt(xp.sum(v * v))


OPS: dict[str, Callable[..., Any]] = {
    "neg": lambda xp, a: -a,
    "add": lambda xp, a, b: a + b,
    "sub": lambda xp, a, b: a - b,
    "mul": _mul,
    "div": lambda xp, a, b: a / b,
    "pow": lambda xp, a, b: a**b,
    "sin": lambda xp, a: xp.sin(a),
    "cos": lambda xp, a: xp.cos(a),
    "tan": lambda xp, a: xp.tan(a),
    "asin": lambda xp, a: xp.arcsin(a),
    "acos": lambda xp, a: xp.arccos(a),
    "atan": lambda xp, a: xp.arctan(a),
    "atan2": lambda xp, a, b: xp.arctan2(a, b),
    "sqrt": lambda xp, a: xp.sqrt(a),
    "abs": lambda xp, a: xp.abs(a),
    "exp": lambda xp, a: xp.exp(a),
    "log": lambda xp, a: xp.log(a),
    # By selection: the derivative of xp.minimum is found by an equality test that XLA's
    # rounding can defeat inside jit (see mbcal.raycast).
    "min": lambda xp, *a: _reduce(lambda u, v: xp.where(u <= v, u, v), a),
    "max": lambda xp, *a: _reduce(lambda u, v: xp.where(u >= v, u, v), a),
    "hypot": lambda xp, a, b: xp.sqrt(a * a + b * b),
    "norm": _safe_norm,
    "dot": lambda xp, a, b: xp.sum(a * b),
    "cross": lambda xp, a, b: xp.cross(a, b),
    "vec": _vec,
    "translate": lambda xp, v: geo.translation(xp, v),
    "rot_x": geo.rot_x,
    "rot_y": geo.rot_y,
    "rot_z": geo.rot_z,
    "rpy": geo.rpy,
    "axis_angle": geo.axis_angle,
    "quat": geo.quaternion,
    "look_at": geo.look_at,
    "compose": lambda xp, a, b: a @ b,
}


def _reduce(fn, values):
    out = values[0]
    for v in values[1:]:
        out = fn(out, v)
    return out


def make_op(
    op: str, args: Sequence[Node], kind: str, dim: Dim | None, size: int = 0, span: SourceSpan | None = None
) -> Node:
    """An operation node — or, when every argument is constant, the folded constant."""
    if all(isinstance(a, Const) for a in args):
        with np.errstate(all="ignore"):
            value = OPS[op](np, *[a.value for a in args])
        return Const(kind=kind, dim=dim, size=size, span=span, value=np.asarray(value, dtype=float))
    return Op(kind=kind, dim=dim, size=size, span=span, op=op, args=tuple(args))


def walk(
    node: Node,
    memo: dict[int, Any],
    const: Callable[[Const], Any],
    param: Callable[[ParamRef], Any],
    op: Callable[..., Any],
) -> Any:
    """Post-order evaluation of a node graph, without recursion: ``const(n)`` and ``param(n)``
    give the leaves' values, ``op(name, *values)`` an operation's.  ``memo`` caches every node's
    value by identity (shared nodes are evaluated once); the walk is iterative, so long chains
    of ``let``s cannot exhaust Python's stack."""
    if id(node) in memo:
        return memo[id(node)]
    stack = [node]
    while stack:
        n = stack[-1]
        key = id(n)
        if key in memo:
            stack.pop()
            continue
        if isinstance(n, Const):
            memo[key] = const(n)
        elif isinstance(n, ParamRef):
            memo[key] = param(n)
        else:
            assert isinstance(n, Op)
            pending = [a for a in n.args if id(a) not in memo]
            if pending:
                stack.extend(pending)
                continue
            memo[key] = op(n.op, *[memo[id(a)] for a in n.args])
        stack.pop()
    return memo[id(node)]


def evaluate(node: Node, X: Any, memo: dict[int, Any], xp: Any = None) -> Any:
    """The value of ``node`` for the parameter vector ``X``.

    ``memo`` caches shared nodes within one evaluation (keyed by node identity); pass the same
    dict for every node of one scene.  ``xp`` is ``jax.numpy`` by default; pass ``numpy`` to
    evaluate eagerly on a numpy ``X``.
    """
    if id(node) in memo:
        return memo[id(node)]
    if xp is None:
        import jax.numpy as jnp

        xp = jnp
    return walk(node, memo, lambda n: n.value, lambda n: X[n.index], lambda name, *a: OPS[name](xp, *a))


def depends_on(node: Node) -> frozenset[int]:
    """Indices of the parameters a node depends on."""
    seen: set[int] = set()
    out: set[int] = set()
    stack = [node]
    while stack:
        n = stack.pop()
        if id(n) in seen:
            continue
        seen.add(id(n))
        if isinstance(n, ParamRef):
            out.add(n.index)
        elif isinstance(n, Op):
            stack.extend(n.args)
    return frozenset(out)
