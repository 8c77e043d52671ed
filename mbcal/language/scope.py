"""Scopes and names: what each name of a model refers to, before anything is compiled.

The first pass (:mod:`mbcal.language.expand`) records every declaration here, in a
:class:`Namespace`; ``let`` definitions, template arguments and parameters are held as
declarations that the expression compiler (:mod:`mbcal.language.expressions`) compiles on first
use, once.

Name look-up (:meth:`Namespace.lookup`):

1. the constant ``pi``;
2. scope by scope, innermost first: its ``let`` definitions and template arguments, then the
   parameter of that name relative to it (inside ``frame room``, ``x`` finds ``room.x``) — a
   template body's scopes are its own and the top level, not the caller's;
3. a parameter by its full name.

A ``let`` or template argument and a parameter of one name in one scope are refused by the first
pass (:mod:`mbcal.language.expand`): neither hides the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mbcal.errors import SourceSpan, UndefinedNameError, suggest
from mbcal.language import ast
from mbcal.language.graph import Node, ParamRef
from mbcal.language.model import ParamInfo

__all__ = ["CONSTANTS", "AXES", "Scope", "Lazy", "ParamDecl", "FrameDecl", "Deferred", "Namespace"]

CONSTANTS = {"pi": math.pi}
# Where an axis is written (a joint's, axis_angle's, look_at's up), x, y and z (or -x, ...) are the
# axes: a let or template argument may not take these names (mbcal.language.expand).
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@dataclass(eq=False)
class Scope:
    """Where a statement stands: inside which frames, templates and ``let``\\ s.

    Attributes
    ----------
    path : str
        Prefix of the names declared here (``""`` at the top level).
    parent : Scope or None
        The enclosing scope whose ``let``\\ s are visible here.
    frame : int
        Index of the frame statements here attach to (-1: the world).
    locals : dict
        ``let`` definitions and template arguments declared here.
    local_spans : dict
        Where each local is declared.
    in_template : bool
        Inside a template body (its parameters are not editable in place).
    """

    path: str
    parent: Scope | None
    frame: int
    locals: dict[str, Lazy] = field(default_factory=dict)
    local_spans: dict[str, SourceSpan] = field(default_factory=dict)
    in_template: bool = False

    def join(self, name: str) -> str:
        """The full name of ``name`` declared in this scope."""
        return f"{self.path}.{name}" if self.path else name


@dataclass(eq=False)
class Lazy:
    """A ``let`` or template argument: compiled on first use, once."""

    what: str
    expr: ast.Expr
    scope: Scope
    node: Node | None = None
    busy: bool = False


@dataclass(eq=False)
class ParamDecl:
    """A parameter statement (one entry of an index range); its value is compiled on first use."""

    stmt: ast.Param
    name: str
    scope: Scope
    index: int
    node: ParamRef | None = None
    info: ParamInfo | None = None
    busy: bool = False


@dataclass(eq=False)
class FrameDecl:
    """A frame (object, link, sensor or target) whose pose is compiled in the second pass."""

    name: str
    parent: int
    pose: ast.Expr | None
    scope: Scope
    keyword: str
    span: SourceSpan


@dataclass(eq=False)
class Deferred:
    """A statement whose expressions are compiled once every parameter is declared."""

    stmt: ast.Statement
    scope: Scope
    frame: int
    name: str = ""


@dataclass(eq=False)
class Namespace:
    """Everything the first pass declares, by full name, and the scopes it was declared in.

    Attributes
    ----------
    path : str
        The model file (``<string>`` for text).
    templates : dict
        Templates by name.
    params : dict
        Parameter declarations by full name, in declaration order.
    frames : list of FrameDecl
        Frames in declaration order (their index is the frame index of the model).
    frame_index : dict
        Frame name → index.
    declared : dict
        Frames, points, sensors and shapes by full name → where declared.
    deferred : list of Deferred
        Points, shapes, cameras, range sensors and targets, compiled in the second pass.
    joints : dict
        Frame index → its joint statement.
    measures : list of str
        The measurement models named by ``measure``.
    measure_spans : list of SourceSpan
        Where each of :attr:`measures` is first named.
    files : list of str
        The model file and every file it includes.
    data_files : list of str
        The other files the model reads: meshes and point files.
    warnings : list of str
        Warnings for the model's summary.
    overrides : dict
        Parameter name → the ``override`` statement that takes effect, and its scope.
    shadowed : list
        The ``override`` statements (with their scopes) that one in an including file replaces:
        checked, not applied.
    global_scope : Scope
        The top level.
    """

    path: str
    templates: dict[str, ast.Template] = field(default_factory=dict)
    params: dict[str, ParamDecl] = field(default_factory=dict)
    frames: list[FrameDecl] = field(default_factory=list)
    frame_index: dict[str, int] = field(default_factory=dict)
    declared: dict[str, SourceSpan] = field(default_factory=dict)
    deferred: list[Deferred] = field(default_factory=list)
    joints: dict[int, Deferred] = field(default_factory=dict)
    measures: list[str] = field(default_factory=list)
    measure_spans: list[SourceSpan] = field(default_factory=list)
    files: list[str] = field(default_factory=list)
    data_files: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    overrides: dict[str, tuple[ast.Override, Scope]] = field(default_factory=dict)
    shadowed: list[tuple[ast.Override, Scope]] = field(default_factory=list)
    global_scope: Scope = field(default_factory=lambda: Scope("", None, -1))

    def lookup(self, name: str, scope: Scope, span: SourceSpan) -> Lazy | ParamDecl | float:
        """What ``name``, used in ``scope``, refers to: a local, a parameter or a constant's value.

        Raises
        ------
        UndefinedNameError
            Nothing visible from ``scope`` has that name (with close matches as a hint).
        """
        if name in CONSTANTS:
            return CONSTANTS[name]
        s: Scope | None = scope
        while s is not None:  # innermost first: a frame's own parameter is not hidden by an outer let
            if name in s.locals:
                return s.locals[name]
            candidate = s.join(name)
            if candidate in self.params:
                return self.params[candidate]
            s = s.parent
        if name in self.params:
            return self.params[name]
        raise UndefinedNameError(f"undefined name '{name}'", span, hint=suggest(name, self.visible(scope)))

    def visible(self, scope: Scope) -> list[str]:
        """The names an expression in ``scope`` may use (for suggestions)."""
        names: list[str] = list(self.params) + list(CONSTANTS)
        s: Scope | None = scope
        while s is not None:
            names.extend(s.locals)
            if s.path:
                names.extend(n[len(s.path) + 1 :] for n in self.params if n.startswith(s.path + "."))
            s = s.parent
        return names
