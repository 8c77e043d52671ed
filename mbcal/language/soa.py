"""Expression evaluation in "structure of arrays" form, for the modeler's hot path.

The values and their arithmetic are in :mod:`mbcal.language.soa_math`; what each operation
computes comes from the catalogue,
:mod:`mbcal.language.functions`.  Constants stay Python floats while tracing, so arithmetic
with exact zeros and ones disappears from the traced program.

The semantics are those of :mod:`mbcal.language.ir`; ``tests/test_modeler.py`` checks that both
evaluations agree.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from mbcal.language.functions import SOA_IMPLEMENTATIONS
from mbcal.language.graph import Node, walk
from mbcal.language.soa_math import from_constant

__all__ = ["OPS", "evaluate"]

OPS: Mapping[str, Callable[..., Any]] = SOA_IMPLEMENTATIONS
"""Operation name → ``f(*args)``: a live view of the catalogue's structure-of-arrays implementations."""


def evaluate(node: Node, X: Any, memo: dict[int, Any]) -> Any:
    """The SoA value of ``node`` for the parameter vector ``X``.

    Parameters
    ----------
    node : Node
        The root of the graph.
    X : array or sequence
        The parameter vector (its entries are the SoA values of the parameters).
    memo : dict
        Caches shared nodes by identity within one evaluation, as in :func:`mbcal.language.ir.evaluate`.

    Returns
    -------
    Any
        A scalar, a tuple of scalars or a transform (R, t); iterative, like the array evaluator.
    """
    return walk(
        node, memo, lambda n: from_constant(n.value, n.kind), lambda n: X[n.index], lambda name, *a: OPS[name](*a)
    )
