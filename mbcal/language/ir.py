"""The resolved, typed expression graph that the modeler evaluates, evaluated with arrays.

The checker turns every expression of a model into a small graph of nodes
(:mod:`mbcal.language.graph`, re-exported here): constants, parameter references and
operations.  Everything that does not depend on a parameter is folded to a numpy constant when
the model is loaded (:func:`make_op`).  Evaluation walks the graph with JAX — mbcal never hands
model text to Python's ``eval``.  What each operation computes comes from the catalogue,
:mod:`mbcal.language.functions`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from mbcal.errors import SourceSpan
from mbcal.language.functions import ARRAY_IMPLEMENTATIONS
from mbcal.language.graph import SCALAR, TRANSFORM, VECTOR, Const, Node, Op, ParamRef, depends_on, walk
from mbcal.units import Dim

__all__ = [
    "Node",
    "Const",
    "ParamRef",
    "Op",
    "SCALAR",
    "VECTOR",
    "TRANSFORM",
    "OPS",
    "make_op",
    "evaluate",
    "walk",
    "depends_on",
]

OPS: Mapping[str, Callable[..., Any]] = ARRAY_IMPLEMENTATIONS
"""Operation name → ``f(xp, *args)``: a live view of the catalogue's array implementations."""


def make_op(
    op: str, args: Sequence[Node], kind: str, dim: Dim | None, size: int = 0, span: SourceSpan | None = None
) -> Node:
    """An operation node — or, when every argument is constant, the folded constant.

    Parameters
    ----------
    op : str
        The operation's name in :mod:`mbcal.language.functions`.
    args : sequence of Node
        Its arguments.
    kind, dim, size, span
        The result's kind, dimension, vector size and source location.

    Returns
    -------
    Node
        A :class:`Const` when every argument is one, else an :class:`Op`.
    """
    constants = [a.value for a in args if isinstance(a, Const)]
    if len(constants) == len(args):
        with np.errstate(all="ignore"):
            value = OPS[op](np, *constants)
        return Const(kind=kind, dim=dim, size=size, span=span, value=np.asarray(value, dtype=float))
    return Op(kind=kind, dim=dim, size=size, span=span, op=op, args=tuple(args))


def evaluate(node: Node, X: Any, memo: dict[int, Any], xp: Any = None) -> Any:
    """The value of ``node`` for the parameter vector ``X``.

    Parameters
    ----------
    node : Node
        The root of the graph.
    X : array
        The parameter vector.
    memo : dict
        Caches shared nodes within one evaluation (keyed by node identity); pass the same dict
        for every node of one scene.
    xp : module, optional
        ``jax.numpy`` by default; pass ``numpy`` to evaluate eagerly on a numpy ``X``.

    Returns
    -------
    array
        A scalar, an (n,) vector or a (4, 4) transform.
    """
    if id(node) in memo:
        return memo[id(node)]
    if xp is None:
        # JAX is heavy: imported on the first traced evaluation, so that `mbcal check` does not pay for it.
        from mbcal._jax import jnp  # float64, whatever the caller imported first

        xp = jnp
    return walk(node, memo, lambda n: n.value, lambda n: X[n.index], lambda name, *a: OPS[name](xp, *a))
