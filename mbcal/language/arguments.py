"""Call arguments matched to a signature.

Shared by everything in the language that takes arguments: function calls, template instances,
and the statements written like calls (joints, shapes, cameras, range sensors, targets).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from mbcal.errors import ArgumentError, SourceSpan, suggest
from mbcal.language import ast

__all__ = ["Parameter", "bind"]


class Parameter(NamedTuple):
    """One formal argument of a signature: its name and whether a call must give it.

    Being a pair, a ``Parameter`` can stand wherever a ``(name, required)`` tuple does.
    """

    name: str
    required: bool = True


def bind(
    fname: str,
    signature: Sequence[tuple[str, bool]],
    args: Sequence[ast.Expr],
    kwargs: Sequence[ast.Keyword],
    span: SourceSpan,
) -> dict[str, ast.Expr]:
    """Match call arguments to a signature.

    Parameters
    ----------
    fname : str
        What is called, for messages (``sqrt``, ``template arm``, ``camera left``).
    signature : sequence of (name, required)
        The formal arguments in positional order (:class:`Parameter` or plain pairs).
    args, kwargs : sequence
        The positional and keyword arguments of the call.
    span : SourceSpan
        The call, for errors that concern it as a whole.

    Returns
    -------
    dict
        Argument name → expression, for the arguments given.

    Raises
    ------
    ArgumentError
        Too many arguments, an unknown or repeated keyword, or a missing required argument.
    """
    names = [n for n, _ in signature]
    required = [n for n, r in signature if r]
    if len(args) > len(names):
        lo, hi = len(required), len(names)
        takes = f"{hi}" if lo == hi else f"{lo} to {hi}"
        listing = f" ({', '.join(names)})" if names else ""
        raise ArgumentError(
            f"{fname}() takes {takes} argument{'s' if hi != 1 else ''}{listing} but {len(args)} were given",
            args[len(names)].span if len(names) < len(args) else span,
        )
    bound: dict[str, ast.Expr] = dict(zip(names, args))
    for kw in kwargs:
        if kw.name not in names:
            raise ArgumentError(
                f"{fname}() has no argument '{kw.name}' (it takes {', '.join(names) or 'none'})",
                kw.span,
                hint=suggest(kw.name, names),
            )
        if kw.name in bound:
            raise ArgumentError(f"{fname}(): argument '{kw.name}' is given twice", kw.span)
        bound[kw.name] = kw.value
    missing = [n for n in required if n not in bound]
    if missing:
        raise ArgumentError(
            f"{fname}() is missing argument{'s' if len(missing) > 1 else ''} {', '.join(repr(m) for m in missing)}",
            span,
        )
    return bound
