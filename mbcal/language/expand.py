"""First pass of the checker: includes and templates expanded, every declaration recorded.

Walking the statements gives every declaration its full dotted name and its scope, instantiates
templates (with their arguments bound, not yet compiled), and refuses duplicate names,
misplaced statements and templates that instantiate themselves.  Nothing is compiled here: the
result is a :class:`~mbcal.language.scope.Namespace` for the second pass.
"""

from __future__ import annotations

from collections.abc import Sequence

from mbcal.errors import DuplicateNameError, MdlError, SourceSpan, UndefinedNameError, suggest
from mbcal.language import ast
from mbcal.language.arguments import bind
from mbcal.language.parse import RESERVED
from mbcal.language.scope import AXES, Deferred, FrameDecl, Lazy, Namespace, ParamDecl, Scope

__all__ = ["expand", "MAX_TEMPLATE_DEPTH", "MAX_FRAMES"]

MAX_TEMPLATE_DEPTH = 64
MAX_FRAMES = 100_000


def expand(statements: Sequence[ast.Statement], path: str) -> Namespace:
    """Record every declaration of a parsed model.

    Parameters
    ----------
    statements : sequence of ast.Statement
        The parsed model, includes resolved.
    path : str
        The model file, for the namespace's list of files.

    Returns
    -------
    Namespace
        Templates, parameters, frames and deferred statements by full name.

    Raises
    ------
    MdlError
        A duplicate or reserved name, a misplaced statement, an unknown template, a template
        that instantiates itself, or too many frames.
    """
    expander = _Expander(Namespace(path, files=[path]))
    expander.collect_templates(statements, True)
    expander.walk(statements, expander.names.global_scope)
    expander.settle_overrides()
    expander.check_locals()
    return expander.names


class _Expander:
    def __init__(self, names: Namespace):
        self.names = names
        self.instantiating: list[str] = []
        self.includes = 0  # include statements walked so far: each one's number names it
        self.chain: list[int] = []  # the includes that lead to the statements being walked
        # Parameter name → its overrides in walk order, each with the includes that lead to it.
        self.overrides: dict[str, list[tuple[ast.Override, Scope, tuple[int, ...]]]] = {}
        # Every let and template argument: (scope, name, where, what it is), checked against the
        # parameters once all are declared (check_locals).
        self.locals: list[tuple[Scope, str, SourceSpan, str]] = []

    def collect_templates(
        self, statements: Sequence[ast.Statement], top: bool, mounted: ast.Include | None = None
    ) -> None:
        """Record the templates; ``mounted``: the include, inside a frame or template, of the file
        whose top level ``statements`` are (for the message: its templates are at the top level of
        their own file)."""
        names = self.names
        for stmt in statements:
            if isinstance(stmt, ast.Template):
                if mounted is not None:
                    raise MdlError(
                        f"template '{stmt.name}' is declared in a file included inside a frame or template "
                        f"(at {mounted.span}): a file that declares templates is included at the top level",
                        stmt.span,
                        hint="move the include out of the frame, or the template to a file included at the top level",
                    )
                if not top:
                    raise MdlError("templates are declared at the top level of a file", stmt.span)
                _check_simple_name(stmt.name, "template", stmt.name_span or stmt.span)
                if stmt.name in names.templates:
                    first = names.templates[stmt.name].span
                    raise DuplicateNameError(f"template '{stmt.name}' is already declared at {first}", stmt.span)
                _check_arguments(stmt)
                names.templates[stmt.name] = stmt
                self.collect_templates(stmt.body, False)  # one declared in it was silently ignored
            elif isinstance(stmt, ast.Include):
                if stmt.resolved:
                    names.files.append(stmt.resolved)
                # a file included inside a frame: the outermost such include is the one to move
                self.collect_templates(stmt.statements, top, None if top else mounted or stmt)
            elif isinstance(stmt, (ast.Frame, ast.Instance)):
                self.collect_templates(stmt.body, False)

    def _declare(self, full: str, span: SourceSpan) -> None:
        declared = self.names.declared
        if full in declared:
            raise DuplicateNameError(f"'{full}' is already declared at {declared[full]}", span)
        declared[full] = span

    def walk(self, statements: Sequence[ast.Statement], scope: Scope, mounted: ast.Include | None = None) -> None:
        """Record the declarations of ``statements`` in ``scope``; ``mounted`` as for
        :meth:`collect_templates`."""
        names = self.names
        for stmt in statements:
            if isinstance(stmt, ast.Include):
                self.includes += 1
                self.chain.append(self.includes)
                inside = bool(scope.path or scope.in_template)
                try:
                    self.walk(stmt.statements, scope, mounted or stmt if inside else None)
                finally:
                    self.chain.pop()
            elif isinstance(stmt, ast.Template):
                continue  # collected before
            elif isinstance(stmt, ast.Param):
                self._walk_param(stmt, scope)
            elif isinstance(stmt, ast.Let):
                _check_simple_name(stmt.name, "let", stmt.name_span or stmt.span)
                if stmt.name in scope.locals:
                    first = scope.local_spans[stmt.name]
                    where = stmt.name_span or stmt.span
                    raise DuplicateNameError(f"'{stmt.name}' is already defined at {first}", where)
                assert stmt.value is not None
                scope.locals[stmt.name] = Lazy(f"let '{stmt.name}'", stmt.value, scope)
                scope.local_spans[stmt.name] = stmt.name_span or stmt.span
                self.locals.append((scope, stmt.name, stmt.name_span or stmt.span, f"let '{stmt.name}'"))
            elif isinstance(stmt, ast.Frame):
                index = self._new_frame(stmt.name, scope, stmt.pose, stmt.keyword, stmt.span, stmt.name_span)
                child = Scope(names.frames[index].name, scope, index, in_template=scope.in_template)
                self.walk(stmt.body, child)
            elif isinstance(stmt, ast.Instance):
                self._walk_instance(stmt, scope)
            elif isinstance(stmt, (ast.Shape, ast.Point)):
                name = stmt.name
                if name is not None:
                    _check_simple_name(name, type(stmt).__name__.lower(), stmt.name_span or stmt.span)
                    self._declare(scope.join(name), stmt.name_span or stmt.span)
                names.deferred.append(Deferred(stmt, scope, scope.frame, scope.join(name) if name else ""))
            elif isinstance(stmt, ast.Joint):
                if scope.frame < 0:
                    raise MdlError("a joint moves a frame: put it inside 'frame NAME { ... }'", stmt.span)
                if scope.frame in names.joints:
                    first = names.joints[scope.frame].stmt.span
                    raise DuplicateNameError(
                        f"frame '{names.frames[scope.frame].name}' already has a joint at {first}", stmt.span
                    )
                names.joints[scope.frame] = Deferred(stmt, scope, scope.frame)
            elif isinstance(stmt, (ast.Camera, ast.RangeSensor, ast.Target)):
                index = self._new_frame(
                    stmt.name, scope, stmt.pose, type(stmt).__name__.lower(), stmt.span, stmt.name_span
                )
                names.deferred.append(Deferred(stmt, scope, index, names.frames[index].name))
            elif isinstance(stmt, ast.Override):
                if mounted is not None:
                    raise MdlError(
                        f"'override' in a file included inside a frame or template (at {mounted.span}): a file "
                        "with overrides is included at the top level",
                        stmt.span,
                        hint="move the include out of the frame, or the override to the including file",
                    )
                if scope.path or scope.in_template:
                    raise MdlError(
                        "'override' is written at the top level of a file, with the full parameter name", stmt.span
                    )
                self.overrides.setdefault(stmt.name, []).append((stmt, scope, tuple(self.chain)))
            elif isinstance(stmt, ast.Measure):
                spans = stmt.kind_spans or (stmt.span,) * len(stmt.kinds)
                for kind, where in zip(stmt.kinds, spans):
                    if kind not in names.measures:
                        names.measures.append(kind)
                        names.measure_spans.append(where)
            else:  # pragma: no cover - every statement type is handled above
                raise MdlError(f"unsupported statement {type(stmt).__name__}", stmt.span)

    def settle_overrides(self) -> None:
        """Decide which ``override`` of each parameter takes effect: the one in a file that
        includes (directly or through other files) the files of all the others.  The others
        are kept in ``names.shadowed``, to be checked but not applied.

        Raises
        ------
        DuplicateNameError
            Two overrides of a parameter neither of which replaces the other: in one file, or in
            files neither of which includes the other.
        """
        names = self.names
        for name, found in self.overrides.items():
            best = min(range(len(found)), key=lambda k: len(found[k][2]))  # the first of the fewest includes
            chain = found[best][2]
            for k, (stmt, scope, under) in enumerate(found):
                if k == best:
                    continue
                if len(under) == len(chain) or under[: len(chain)] != chain:
                    first, second = found[min(k, best)][0], found[max(k, best)][0]
                    raise DuplicateNameError(
                        f"'{name}' is already overridden at {first.span}",
                        second.name_span or second.span,
                        hint="an override replaces only one in a file it includes",
                    )
                names.shadowed.append((stmt, scope))
            names.overrides[name] = found[best][:2]

    def check_locals(self) -> None:
        """Refuse a ``let`` or template argument with the name of a parameter of its scope: the
        one would hide the other (``param x`` and ``let x`` in one frame: ``x`` was the let); and a
        ``let`` named like an axis."""
        params = self.names.params
        for scope, name, where, what in self.locals:
            decl = params.get(scope.join(name))
            if decl is not None:
                raise DuplicateNameError(
                    f"{what} has the name of parameter '{decl.name}' declared at {decl.stmt.span}",
                    where,
                    hint="a name means one thing in a scope: rename one of them",
                )
            if what.startswith("let"):  # a template's arguments are checked where it is declared
                _check_not_an_axis(name, "let", where)

    def _new_frame(
        self,
        name: str,
        scope: Scope,
        pose: ast.Expr | None,
        keyword: str,
        span: SourceSpan,
        name_span: SourceSpan | None = None,
    ) -> int:
        frames = self.names.frames
        _check_simple_name(name, "frame", name_span or span)
        full = scope.join(name)
        self._declare(full, name_span or span)
        if len(frames) >= MAX_FRAMES:
            raise MdlError(f"more than {MAX_FRAMES} frames: is a template instantiating itself?", span)
        frames.append(FrameDecl(full, scope.frame, pose, scope, keyword, span))
        self.names.frame_index[full] = len(frames) - 1
        return len(frames) - 1

    def _walk_param(self, stmt: ast.Param, scope: Scope) -> None:
        params = self.names.params
        names = [stmt.name]
        if stmt.index_range is not None:
            lo, hi = stmt.index_range
            names = [f"{stmt.name}{i}" for i in range(lo, hi + 1)]
        if stmt.name in RESERVED:
            raise MdlError(f"'{stmt.name}' is a reserved word and cannot name a parameter", stmt.name_span or stmt.span)
        last = stmt.name.rsplit(".", 1)[-1]
        if last in ("pi", "inf"):  # inside frame f, 'pi' is the constant, not f.pi: one would be hidden
            raise MdlError(
                f"'{last}' is a reserved word and cannot end a parameter name: '{stmt.name}'",
                stmt.name_span or stmt.span,
            )
        for name in names:
            full = scope.join(name)
            if full in params:
                first = params[full].stmt.span
                raise DuplicateNameError(
                    f"parameter '{full}' is already declared at {first}", stmt.name_span or stmt.span
                )
            params[full] = ParamDecl(stmt, full, scope, len(params))

    def _walk_instance(self, stmt: ast.Instance, scope: Scope) -> None:
        names = self.names
        template = names.templates.get(stmt.template)
        if template is None:
            raise UndefinedNameError(
                f"no template named '{stmt.template}'",
                stmt.template_span or stmt.span,
                hint=suggest(stmt.template, names.templates),
            )
        if stmt.template in self.instantiating:
            chain = " -> ".join([*self.instantiating, stmt.template])
            raise MdlError(f"template instantiates itself: {chain}", stmt.span)
        if len(self.instantiating) >= MAX_TEMPLATE_DEPTH:
            raise MdlError(f"templates nested deeper than {MAX_TEMPLATE_DEPTH}", stmt.span)
        index = self._new_frame(stmt.name, scope, stmt.pose, stmt.keyword, stmt.span, stmt.name_span)
        full = names.frames[index].name
        inner = Scope(full, names.global_scope, index, in_template=True)
        signature = [(p.name, p.default is None) for p in template.params]
        bound = bind(f"template {template.name}", signature, stmt.args, stmt.kwargs, stmt.span)
        for p in template.params:
            if p.name in bound:
                inner.locals[p.name] = Lazy(f"argument '{p.name}'", bound[p.name], scope)
            else:
                assert p.default is not None  # bind() refuses a missing argument without a default
                inner.locals[p.name] = Lazy(f"argument '{p.name}'", p.default, inner)
            inner.local_spans[p.name] = p.span
            self.locals.append((inner, p.name, p.span, f"argument '{p.name}' of template '{template.name}'"))
        self.instantiating.append(stmt.template)
        try:
            self.walk(template.body, inner)
        finally:
            self.instantiating.pop()
        if stmt.body:
            self.walk(stmt.body, Scope(full, scope, index, in_template=scope.in_template))


def _check_arguments(template: ast.Template) -> None:
    """Refuse two arguments of one name in a template's declaration (the second was bound in
    place of the first: ``template t(a, a)`` took ``t(1 m, 2 m)`` as a = 2 m)."""
    seen: dict[str, SourceSpan] = {}
    for p in template.params:
        _check_simple_name(p.name, "template argument", p.span)
        _check_not_an_axis(p.name, "template argument", p.span)
        if p.name in seen:
            raise DuplicateNameError(
                f"argument '{p.name}' of template '{template.name}' is already declared at {seen[p.name]}", p.span
            )
        seen[p.name] = p.span


def _check_not_an_axis(name: str, what: str, span: SourceSpan) -> None:
    """Refuse ``let z = ...``: where an axis is written, ``z`` is the z axis, so the let was used
    everywhere else but there (a parameter is a number, never an axis: it may be called ``z``)."""
    if name in AXES:
        raise MdlError(
            f"'{name}' is the {name} axis where an axis is written (joint, axis_angle, look_at's up) "
            f"and cannot name a {what}",
            span,
            hint=f"give the {what} another name; an axis may be any 3-vector: joint revolute(my_axis, q)",
        )


def _check_simple_name(name: str, what: str, span: SourceSpan) -> None:
    if "." in name:
        raise MdlError(f"a {what} name cannot contain '.': '{name}'", span)
    if name in RESERVED:
        raise MdlError(f"'{name}' is a reserved word and cannot name a {what}", span)
