"""The syntax tree of a model description: what the text says, before names are resolved.

Nodes are frozen dataclasses holding plain Python values (``str``, ``float``, tuples) and our
own :class:`~mbcal.errors.SourceSpan`, so two trees parsed from the same text compare equal.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field

from mbcal.errors import SourceSpan


@contextlib.contextmanager
def deep_recursion(limit: int = 8000) -> Iterator[None]:
    """Allow the recursive walks over a (depth-checked) syntax tree more stack than Python's default."""
    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, limit))
    try:
        yield
    finally:
        sys.setrecursionlimit(old)


# ---- expressions --------------------------------------------------------------------------


@dataclass(frozen=True)
class Expr:
    """Base of expression nodes."""

    span: SourceSpan = field(compare=False, repr=False)


@dataclass(frozen=True)
class Number(Expr):
    """A literal, ``value`` in the unit ``unit`` (None: no unit written)."""

    value: float = 0.0
    unit: str | None = None


@dataclass(frozen=True)
class Name(Expr):
    """A (possibly dotted) name: a parameter, a ``let``, a template argument or a constant."""

    name: str = ""


@dataclass(frozen=True)
class String(Expr):
    """A string literal (file names)."""

    value: str = ""


@dataclass(frozen=True)
class Unary(Expr):
    """``-operand``."""

    op: str = "-"
    operand: Expr | None = None


@dataclass(frozen=True)
class Binary(Expr):
    """``left op right`` with op one of ``+ - * / ^``."""

    op: str = "+"
    left: Expr | None = None
    right: Expr | None = None


@dataclass(frozen=True)
class Keyword:
    """``name = value`` inside a call's argument list."""

    name: str
    value: Expr
    span: SourceSpan = field(compare=False, repr=False)


@dataclass(frozen=True)
class Call(Expr):
    """``func(args..., name = value, ...)``."""

    func: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()


@dataclass(frozen=True)
class Vector(Expr):
    """``(a, b, c)``: a vector of two or more components."""

    items: tuple[Expr, ...] = ()


@dataclass(frozen=True)
class List(Expr):
    """``[a, b, ...]``: a list (of directions, for instance)."""

    items: tuple[Expr, ...] = ()


# ---- statements ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Statement:
    """Base of statement nodes; ``name_span`` locates the declared name, where there is one."""

    span: SourceSpan = field(compare=False, repr=False)
    name_span: SourceSpan | None = field(default=None, compare=False, repr=False, kw_only=True)


@dataclass(frozen=True)
class Include(Statement):
    """``include "file.mdl"``; ``statements`` is filled in when the file is loaded."""

    path: str = ""
    resolved: str | None = None
    statements: tuple[Statement, ...] = ()


@dataclass(frozen=True)
class Param(Statement):
    """``param name[i..j] = value in [lo, hi] [bounded] [limits [a, b]] sigma s per configuration``."""

    name: str = ""
    value: Expr | None = None
    index_range: tuple[int, int] | None = None
    lower: Expr | None = None
    upper: Expr | None = None
    sigma: Expr | None = None
    per_configuration: bool = False
    bounded: bool = False  # ``in [lo, hi] bounded``: the search range is also the hard limits
    limit_lower: Expr | None = None  # ``limits [a, b]``: hard limits (``inf``/``-inf`` leave a side open)
    limit_upper: Expr | None = None
    limits_span: SourceSpan | None = None  # where ``bounded`` or ``limits [...]`` stands


@dataclass(frozen=True)
class Override(Statement):
    """``override name = value [sigma s]``: a new nominal value for a parameter declared elsewhere."""

    name: str = ""
    value: Expr | None = None
    sigma: Expr | None = None


@dataclass(frozen=True)
class Let(Statement):
    """``let name = expr``: a named expression, evaluated with the parameters."""

    name: str = ""
    value: Expr | None = None


@dataclass(frozen=True)
class TemplateParam:
    """One formal argument of a template, with an optional default."""

    name: str
    default: Expr | None
    span: SourceSpan = field(compare=False, repr=False)


@dataclass(frozen=True)
class Template(Statement):
    """``template name(a, b = default) { body }``."""

    name: str = ""
    params: tuple[TemplateParam, ...] = ()
    body: tuple[Statement, ...] = ()


@dataclass(frozen=True)
class Frame(Statement):
    """``frame|object|link name at pose { body }``."""

    keyword: str = "frame"
    name: str = ""
    pose: Expr | None = None
    body: tuple[Statement, ...] = ()


@dataclass(frozen=True)
class Instance(Statement):
    """``object name = template(args) at pose { extra body }``."""

    keyword: str = "object"
    name: str = ""
    template: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()
    pose: Expr | None = None
    body: tuple[Statement, ...] = ()
    template_span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Shape(Statement):
    """``shape [name =] kind(args) at pose``."""

    name: str | None = None
    kind: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()
    pose: Expr | None = None
    kind_span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Point(Statement):
    """``point name = (x, y, z)`` in the enclosing frame."""

    name: str = ""
    value: Expr | None = None


@dataclass(frozen=True)
class Joint(Statement):
    """``joint revolute|prismatic(axis, q, offset = ..., lower = ..., upper = ...)``."""

    kind: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()


@dataclass(frozen=True)
class Sensor(Statement):
    """A sensor statement: ``KEYWORD name(arguments) at pose`` (see its subclasses)."""

    name: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()
    pose: Expr | None = None


@dataclass(frozen=True)
class Camera(Sensor):
    """``camera name(width = ..., height = ..., f = ..., ...) at pose``."""


@dataclass(frozen=True)
class RangeSensor(Sensor):
    """``range name(direction = ... | directions = [...] | fov = ..., rays = ...) at pose``."""


@dataclass(frozen=True)
class Target(Statement):
    """``target name = chessboard(...) at pose``: a frame holding a grid of named points."""

    name: str = ""
    kind: str = ""
    args: tuple[Expr, ...] = ()
    kwargs: tuple[Keyword, ...] = ()
    pose: Expr | None = None
    kind_span: SourceSpan | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class Measure(Statement):
    """``measure image_point, range``: the measurement models this model is meant for."""

    kinds: tuple[str, ...] = ()
    kind_spans: tuple[SourceSpan, ...] = field(default=(), compare=False, repr=False)
