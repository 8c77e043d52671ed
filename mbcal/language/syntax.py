"""Text → syntax tree with Lark: the parser, its error messages, and the tree → :mod:`ast` nodes.

Imported only when a model text is not in the parsed-model cache (:mod:`mbcal.language.parse`):
Lark's import, its tables and the parse were ~0.06 s of every command that loads a model.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import lark
from lark import Lark, Token, Transformer, v_args
from lark.exceptions import UnexpectedCharacters, UnexpectedEOF, UnexpectedInput, UnexpectedToken, VisitError

from mbcal.cache import cache_dir
from mbcal.errors import MbcalError, MdlSyntaxError, SourceSpan
from mbcal.language import ast
from mbcal.language.ast import deep_recursion
from mbcal.resources import grammar_path

__all__ = ["statements", "MAX_TREE_DEPTH"]

# Deepest syntax tree accepted (operators, calls, frames): deeper input is refused with a located
# error before any recursive walk can overflow Python's stack.  Every operator of a chain
# (a + b + c ...) is a level of the tree: a sum of 300 terms is that deep.  The walks need about
# 1 kB of C stack a level: 300 levels load in a thread of 256 kB of stack (600 did not).
MAX_TREE_DEPTH = 300
# The tree's expression nodes: a too-deep path is reported at its outermost expression.
_EXPRESSIONS = frozenset(
    {"add", "sub", "mul", "div", "pow", "neg", "call", "arguments", "keyword_argument", "vector", "list"}
)


def statements(text: str, path: str) -> tuple[ast.Statement, ...]:
    """The statements of ``text`` (checked by :func:`mbcal.language.parse.parse_text` for size and
    nesting), parsed by Lark; an :class:`~mbcal.errors.MdlSyntaxError` located in ``path`` when
    it does not parse."""
    try:
        tree = _parser().parse(text)
    except UnexpectedInput as err:
        raise _syntax_error(err, path, text) from None
    _check_depth(tree, path)
    try:
        with deep_recursion():
            return _ToAst(path).transform(tree)
    except VisitError as err:
        if isinstance(err.orig_exc, MbcalError):
            raise err.orig_exc from None
        raise


@functools.lru_cache(maxsize=1)
def _parser() -> Lark:
    # Building the LALR tables takes ~0.1 s of every command's start-up: Lark keeps them in a file
    # in mbcal's cache folder, checked against a hash of the grammar, options and Lark's version
    # (a stale or unreadable file is rebuilt).
    return Lark(
        grammar_path().read_text(encoding="utf-8"),
        parser="lalr",
        lexer="contextual",
        propagate_positions=True,
        maybe_placeholders=True,
        cache=_parser_cache_file() or False,
    )


def _parser_cache_file() -> str | None:
    folder = cache_dir()
    if folder is None:
        return None
    try:
        (folder / "lark").mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # an unwritable home: build the tables every time
    return str(folder / "lark" / "mdl-grammar.lark")


# Readable names for terminals in "expected ..." messages.
_TERMINAL_NAMES = {
    "NAME": "a name",
    "NUMBER": "a number",
    "STRING": "a string",
    "UNIT": "a unit",
    "FRAME_KEYWORD": "'frame'/'object'/'link'",
    "LPAR": "'('",
    "RPAR": "')'",
    "LSQB": "'['",
    "RSQB": "']'",
    "LBRACE": "'{'",
    "RBRACE": "'}'",
    "COMMA": "','",
    "EQUAL": "'='",
    "SEMICOLON": "';'",
    "PLUS": "'+'",
    "MINUS": "'-'",
    "STAR": "'*'",
    "SLASH": "'/'",
    "CIRCUMFLEX": "'^'",
    "$END": "end of file",
}


def _describe_terminal(name: str) -> str:
    if name in _TERMINAL_NAMES:
        return _TERMINAL_NAMES[name]
    try:
        pattern = _parser().get_terminal(name).pattern
    except KeyError:
        return name
    if isinstance(pattern, lark.lexer.PatternStr):
        return f"'{pattern.value}'"
    return name.lower()


def _expected(names: set[str] | frozenset[str]) -> str:
    described = sorted({_describe_terminal(n) for n in names})
    if len(described) > 8:
        return ", ".join(described[:8]) + ", ..."
    return ", ".join(described)


def _syntax_error(err: UnexpectedInput, path: str, text: str) -> MdlSyntaxError:
    line = getattr(err, "line", None) or 1
    column = getattr(err, "column", None) or 1
    if isinstance(err, UnexpectedCharacters):
        pos = err.pos_in_stream
        char = text[pos] if pos is not None and pos < len(text) else ""
        message = f"unexpected character {char!r}"
        if err.allowed:
            message += f"; expected {_expected(err.allowed)}"
    elif isinstance(err, UnexpectedEOF):
        lines = text.splitlines() or [""]
        line, column = len(lines), len(lines[-1]) + 1
        message = f"unexpected end of file; expected {_expected(set(err.expected))}"
    elif isinstance(err, UnexpectedToken):
        token = err.token
        if token.type == "$END":
            lines = text.splitlines() or [""]
            line, column = len(lines), len(lines[-1]) + 1
            message = "unexpected end of file"
        else:
            message = f"unexpected {_describe_token(token)}"
        if err.expected:
            message += f"; expected {_expected(err.expected)}"
    else:  # pragma: no cover - Lark has no other UnexpectedInput subclasses today
        message = str(err)
    return MdlSyntaxError(message, SourceSpan(path, line, column, line, column + 1))


def _describe_token(token: Token) -> str:
    if token.type == "NAME":
        return f"name '{token}'"
    if token.type == "NUMBER":
        return f"number {token}"
    if token.type == "STRING":
        return f"string {token}"
    return f"'{token}'"


class _ToAst(Transformer):
    """Lark tree → :mod:`mbcal.language.ast` nodes."""

    def __init__(self, path: str):
        super().__init__()
        self.path = path

    def _span(self, meta) -> SourceSpan:
        if getattr(meta, "empty", True):
            return SourceSpan(self.path, 1, 1)
        return SourceSpan(self.path, meta.line, meta.column, meta.end_line, meta.end_column)

    def _tspan(self, token: Token) -> SourceSpan:
        # Tokens from the parser always carry their position; 1 keeps the type honest.
        return SourceSpan(self.path, token.line or 1, token.column or 1, token.end_line, token.end_column)

    # -- expressions
    @v_args(meta=True)
    def number(self, meta, children):
        value, unit = children
        return ast.Number(span=self._span(meta), value=float(value), unit=str(unit) if unit else None)

    @v_args(meta=True)
    def name(self, meta, children):
        return ast.Name(span=self._span(meta), name=str(children[0]))

    @v_args(meta=True)
    def string(self, meta, children):
        return ast.String(span=self._span(meta), value=_unquote(str(children[0])))

    @v_args(meta=True)
    def neg(self, meta, children):
        return ast.Unary(span=self._span(meta), op="-", operand=children[0])

    @staticmethod  # a small factory called while the class body runs
    def _binary(op: str) -> Callable[..., ast.Binary]:
        @v_args(meta=True)
        def method(self, meta, children):
            return ast.Binary(span=self._span(meta), op=op, left=children[0], right=children[1])

        return method

    add = _binary("+")
    sub = _binary("-")
    mul = _binary("*")
    div = _binary("/")
    pow = _binary("^")

    @v_args(meta=True)
    def call(self, meta, children):
        func, arguments = children
        args, kwargs = arguments if arguments is not None else ((), ())
        return ast.Call(span=self._span(meta), func=str(func), args=args, kwargs=kwargs)

    @v_args(meta=True)
    def vector(self, meta, children):
        return ast.Vector(span=self._span(meta), items=tuple(c for c in children if c is not None))

    @v_args(meta=True)
    def list(self, meta, children):
        return ast.List(span=self._span(meta), items=tuple(c for c in children if c is not None))

    @v_args(meta=True)
    def keyword_argument(self, meta, children):
        return ast.Keyword(name=str(children[0]), value=children[1], span=self._span(meta))

    def arguments(self, children):
        args: list[ast.Expr] = []
        kwargs: list[ast.Keyword] = []
        for child in children:
            if child is None:
                continue
            if isinstance(child, ast.Keyword):
                kwargs.append(child)
            elif kwargs:
                raise MdlSyntaxError("a positional argument cannot follow a keyword argument", child.span)
            else:
                args.append(child)
        return tuple(args), tuple(kwargs)

    # -- statements
    @v_args(meta=True)
    def include(self, meta, children):
        return ast.Include(span=self._span(meta), path=_unquote(str(children[0])))

    @v_args(meta=True)
    def param(self, meta, children):
        name, index_range, value, prange, limits, sigma, per_config = children
        lower, upper, bounded, bounded_span = prange if prange is not None else (None, None, False, None)
        limit_lower, limit_upper, limits_span = limits if limits is not None else (None, None, bounded_span)
        return ast.Param(
            span=self._span(meta),
            name_span=self._tspan(name),
            name=str(name),
            value=value,
            index_range=index_range,
            lower=lower,
            upper=upper,
            sigma=sigma,
            per_configuration=per_config is not None,
            bounded=bounded,
            limit_lower=limit_lower,
            limit_upper=limit_upper,
            limits_span=limits_span,
        )

    @v_args(meta=True)
    def index_range(self, meta, children):
        first, last = children
        span = self._span(meta)
        for token in (first, last):
            if not str(token).isdigit():
                raise MdlSyntaxError(f"an index range needs whole numbers, got {token}", self._tspan(token))
        lo, hi = int(first), int(last)
        if hi < lo:
            raise MdlSyntaxError(f"empty index range [{lo}..{hi}]", span)
        if hi - lo >= 10000:
            raise MdlSyntaxError(f"index range [{lo}..{hi}] is too long (at most 10000 entries)", span)
        return (lo, hi)

    @v_args(meta=True)
    def override(self, meta, children):
        name, value, sigma = children
        return ast.Override(
            span=self._span(meta), name_span=self._tspan(name), name=str(name), value=value, sigma=sigma
        )

    def param_range(self, children):
        lower, upper, bounded = children
        return (lower, upper, bounded is not None, bounded)

    @v_args(meta=True)
    def bounded(self, meta, children):
        return self._span(meta)

    @v_args(meta=True)
    def param_limits(self, meta, children):
        return (children[0], children[1], self._span(meta))

    def param_sigma(self, children):
        return children[0]

    def per_config(self, children):
        return True

    @v_args(meta=True)
    def let(self, meta, children):
        return ast.Let(
            span=self._span(meta), name_span=self._tspan(children[0]), name=str(children[0]), value=children[1]
        )

    @v_args(meta=True)
    def template_param(self, meta, children):
        return ast.TemplateParam(name=str(children[0]), default=children[1], span=self._span(meta))

    @v_args(meta=True)
    def template(self, meta, children):
        name, *rest = children
        body = rest[-1]
        params = tuple(p for p in rest[:-1] if p is not None)
        return ast.Template(
            span=self._span(meta), name_span=self._tspan(name), name=str(name), params=params, body=body
        )

    def block(self, children):
        return tuple(c for c in children if isinstance(c, ast.Statement))

    def pose(self, children):
        return children[0]

    @v_args(meta=True)
    def frame(self, meta, children):
        keyword, name, pose, body = children
        return ast.Frame(
            span=self._span(meta),
            name_span=self._tspan(name),
            keyword=str(keyword),
            name=str(name),
            pose=pose,
            body=body or (),
        )

    @v_args(meta=True)
    def instance(self, meta, children):
        keyword, name, template, arguments, pose, body = children
        args, kwargs = arguments if arguments is not None else ((), ())
        return ast.Instance(
            span=self._span(meta),
            name_span=self._tspan(name),
            keyword=str(keyword),
            name=str(name),
            template=str(template),
            args=args,
            kwargs=kwargs,
            pose=pose,
            body=body or (),
            template_span=self._tspan(template),
        )

    def _kind_call(self, node_type: type, meta, name, kind, arguments, pose) -> Any:
        """A ``[name =] kind(arguments) at pose`` statement (shapes, targets)."""
        args, kwargs = arguments if arguments is not None else ((), ())
        return node_type(
            span=self._span(meta),
            name_span=self._tspan(name) if name is not None else None,
            name=str(name) if name is not None else None,
            kind=str(kind),
            args=args,
            kwargs=kwargs,
            pose=pose,
            kind_span=self._tspan(kind),
        )

    @v_args(meta=True)
    def shape(self, meta, children):
        if len(children) == 4:
            name, kind, arguments, pose = children
        else:  # pragma: no cover - the grammar always yields the optional name slot
            name, (kind, arguments, pose) = None, children
        return self._kind_call(ast.Shape, meta, name, kind, arguments, pose)

    @v_args(meta=True)
    def point(self, meta, children):
        return ast.Point(
            span=self._span(meta), name_span=self._tspan(children[0]), name=str(children[0]), value=children[1]
        )

    @staticmethod  # as _binary
    def _call_statement(node_type: type) -> Callable[..., Any]:
        @v_args(meta=True)
        def method(self, meta, children):
            name, arguments, *rest = children
            args, kwargs = arguments if arguments is not None else ((), ())
            extra = {"pose": rest[0]} if rest else {}
            key = "kind" if node_type is ast.Joint else "name"
            return node_type(
                span=self._span(meta),
                name_span=self._tspan(name),
                args=args,
                kwargs=kwargs,
                **{key: str(name)},
                **extra,
            )

        return method

    joint = _call_statement(ast.Joint)
    camera = _call_statement(ast.Camera)
    range_sensor = _call_statement(ast.RangeSensor)

    @v_args(meta=True)
    def target(self, meta, children):
        return self._kind_call(ast.Target, meta, *children)

    @v_args(meta=True)
    def measure(self, meta, children):
        return ast.Measure(
            span=self._span(meta),
            kinds=tuple(str(c) for c in children),
            kind_spans=tuple(self._tspan(c) for c in children),
        )

    def start(self, children):
        return tuple(c for c in children if isinstance(c, ast.Statement))


def _unquote(text: str) -> str:
    body = text[1:-1]
    out: list[str] = []
    i = 0
    while i < len(body):
        ch = body[i]
        if ch == "\\" and i + 1 < len(body):
            nxt = body[i + 1]
            out.append({"n": "\n", "t": "\t", '"': '"', "\\": "\\"}.get(nxt, nxt))
            i += 2
        else:
            out.append(ch)
            i += 1
    return "".join(out)


def _check_depth(tree: lark.Tree, path: str) -> None:
    """Refuse trees deeper than MAX_TREE_DEPTH (iteratively: no recursion here), located at the
    outermost expression of the too-deep path (a statement's whole sum, not one of its terms)."""
    stack: list[tuple[lark.Tree, int, lark.Tree | None]] = [(tree, 1, None)]
    while stack:
        node, depth, root = stack.pop()
        if root is None and node.data in _EXPRESSIONS:
            root = node
        if depth > MAX_TREE_DEPTH:
            meta = getattr(root if root is not None else node, "meta", None)
            line = getattr(meta, "line", 1) or 1
            column = getattr(meta, "column", 1) or 1
            span = SourceSpan(path, line, column, getattr(meta, "end_line", None), getattr(meta, "end_column", None))
            if root is None:  # a frame and its { block } are two levels
                raise MdlSyntaxError(f"frames nested too deeply (at most about {MAX_TREE_DEPTH // 2})", span)
            raise MdlSyntaxError(
                f"expression too deep: more than {MAX_TREE_DEPTH} levels of operators, calls and vectors "
                "(each operator of a chain a + b + c + ... is one)",
                span,
                hint="split it with lets: let part1 = a + b + ...",
            )
        for child in node.children:
            if isinstance(child, lark.Tree):
                stack.append((child, depth + 1, root))
