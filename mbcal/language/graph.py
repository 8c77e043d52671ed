"""The expression graph: its nodes, their kinds and dimensions, and a walk over them.

The checker turns every expression of a model into a small graph of :class:`Node` objects:
constants, parameter references and operations.  Names are resolved (a ``let`` or template
argument used twice is one shared node, evaluated once) and every node knows its kind (scalar,
vector, transform) and its dimension.  This module holds only the data; what an operation
computes is in :mod:`mbcal.language.functions`, and the two evaluators are
:mod:`mbcal.language.ir` (arrays) and :mod:`mbcal.language.soa` (structure of arrays).
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from mbcal.errors import SourceSpan
from mbcal.units import DIMENSIONLESS, Dim

__all__ = [
    "SCALAR",
    "VECTOR",
    "TRANSFORM",
    "Node",
    "Const",
    "ParamRef",
    "Op",
    "walk",
    "depends_on",
    "describe_kind",
    "product_dim",
    "quotient_dim",
]

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
        """Whether the node's value is known when the model is loaded."""
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
    """The operation named ``op`` (see :mod:`mbcal.language.functions`) applied to ``args``."""

    op: str = ""
    args: tuple[Node, ...] = ()


def walk(
    node: Node,
    memo: dict[int, Any],
    const: Callable[[Const], Any],
    param: Callable[[ParamRef], Any],
    op: Callable[..., Any],
) -> Any:
    """Evaluate a node graph in post-order, without recursion.

    Parameters
    ----------
    node : Node
        The root.
    memo : dict
        Every node's value by identity, so shared nodes are evaluated once; filled in place.
    const, param : callable
        The value of a leaf: ``const(n)`` for a :class:`Const`, ``param(n)`` for a :class:`ParamRef`.
    op : callable
        ``op(name, *values)``: the value of an operation from its arguments' values.

    Returns
    -------
    Any
        The root's value.  The walk is iterative, so long chains of ``let``\\ s cannot exhaust
        Python's stack.
    """
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


def depends_on(node: Node) -> frozenset[int]:
    """Indices of the parameters a node depends on.

    Parameters
    ----------
    node : Node
        The root of the graph.

    Returns
    -------
    frozenset of int
        Positions in the parameter vector.
    """
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


def describe_kind(node: Node) -> str:
    """A node's kind for messages: ``a scalar``, ``a 3-vector``, ``a transform``."""
    if node.kind == VECTOR:
        return f"a {node.size}-vector"
    return f"a {node.kind}"


def product_dim(a: Dim | None, b: Dim | None) -> Dim | None:
    """The dimension of a product; a unitless literal (None) takes the other factor's."""
    if a is None:
        return b
    if b is None:
        return a
    return a * b


def quotient_dim(a: Dim | None, b: Dim | None) -> Dim | None:
    """The dimension of a quotient; a unitless literal (None) counts as dimensionless on top."""
    if b is None:
        return a
    return (a if a is not None else DIMENSIONLESS) / b


# ---- what a parameter declared without a unit is used as ------------------------------------------

# A literal without a unit is free: it takes the dimension its place needs.  A parameter declared
# so has no dimension of its own, but where it stands decides what a value given later (--set, a
# measurement file's known value) may be written in: 30 cm for a box's size, never 600 mm for a
# focal length in pixels.
_USES: contextvars.ContextVar[dict[int, set[Dim]] | None] = contextvars.ContextVar("mbcal_param_uses", default=None)
# Operations whose result has their arguments' dimension: a parameter inside stands where it does.
_SAME_DIMENSION = frozenset({"vec", "add", "sub", "neg"})


@contextlib.contextmanager
def recording_uses() -> Iterator[dict[int, set[Dim]]]:
    """Within the block, :func:`note_use` records, per parameter index, the dimensions the places of
    the parameters declared without a unit require."""
    uses: dict[int, set[Dim]] = {}
    token = _USES.set(uses)
    try:
        yield uses
    finally:
        _USES.reset(token)


def note_use(node: Node, dim: Dim | None) -> None:
    """``node`` stands where ``dim`` is required (its check passed): a parameter without a unit found
    there — itself, a component of a vector, a term of a sum, negated — is used as ``dim``."""
    uses = _USES.get()
    if uses is None or dim is None:
        return
    stack = [node]
    while stack:
        n = stack.pop()
        if isinstance(n, ParamRef) and n.dim is None:
            uses.setdefault(n.index, set()).add(dim)
        elif isinstance(n, Op) and n.op in _SAME_DIMENSION:
            stack.extend(n.args)
