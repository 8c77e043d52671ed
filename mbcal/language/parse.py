"""Text → syntax tree: checks of the text, the parsed-model cache, and ``include`` resolution.

The Lark parser itself is in :mod:`mbcal.language.syntax`, imported only when a text is not in
the cache folder's ``syntax/`` part (:func:`mbcal.cache.cache_dir`): the statements of a file
once parsed are kept there, keyed by its text, its displayed path (every node's
``file:line:col``), the grammar, the code that builds them and Lark's install.  Lark's import,
its tables and the parse were ~0.06 s of every command that loads a model; the stored
statements load in well under a millisecond (issue 16).  Only texts that parsed are kept.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import json
import os
import re
import sys
from pathlib import Path

from mbcal import errors as _errors
from mbcal.cache import CACHE_PARTS, Hasher, cache_dir, source_edited
from mbcal.errors import IncludeError, MdlSyntaxError, SourceSpan, remember_source, undecodable_at
from mbcal.language import ast, files
from mbcal.language.ast import deep_recursion
from mbcal.outputs import atomic_write
from mbcal.resources import grammar_path

__all__ = [
    "grammar_path",
    "grammar_text",
    "parse_text",
    "parse_text_cached",
    "display_path",
    "parse_text_with_includes",
    "parse_file",
    "deep_recursion",
    "RESERVED",
    "MAX_INCLUDE_DEPTH",
]

# The language's keywords and the names it gives a value (pi; inf, an open end of limits [...]): no
# name may be one of them (docs/language.md lists them).
RESERVED = frozenset(
    {
        "include", "param", "let", "template", "frame", "object", "link", "shape", "point",
        "joint", "camera", "range", "target", "measure", "override", "at", "in", "sigma", "per",
        "configuration", "pi", "inf", "world", "bounded", "limits",
    }
)  # fmt: skip

MAX_INCLUDE_DEPTH = 32
# Guard against pathological inputs (deep parentheses make Lark's and our own recursion deep).
MAX_SOURCE_BYTES = 8 * 1024 * 1024
MAX_NESTING = 200
# A code point of UTF-16's surrogate range: not a character, and not encodable as UTF-8.
_SURROGATE = re.compile("[\ud800-\udfff]")


def grammar_text() -> str:
    """The grammar, as mbcal uses it."""
    return grammar_path().read_text(encoding="utf-8")


def _check_nesting(text: str, path: str) -> None:
    """Refuse absurdly deep nesting before Lark and our tree walkers recurse into it."""
    depth = 0
    line, col = 1, 0
    for ch in text:
        col += 1
        if ch == "\n":
            line, col = line + 1, 0
        elif ch in "([{":
            depth += 1
            if depth > MAX_NESTING:
                raise MdlSyntaxError(
                    f"nesting deeper than {MAX_NESTING} levels of brackets", SourceSpan(path, line, col)
                )
        elif ch in ")]}":
            depth = max(0, depth - 1)


def parse_text(text: str, path: str = "<string>") -> tuple[ast.Statement, ...]:
    """Parse model text into statements (includes are left unresolved).

    Raises
    ------
    MdlSyntaxError
        With the location of the first offending token.
    """
    remember_source(path, text)
    if len(text.encode("utf-8", errors="replace")) > MAX_SOURCE_BYTES:
        raise MdlSyntaxError(f"file is larger than {MAX_SOURCE_BYTES // (1024 * 1024)} MiB", SourceSpan(path, 1, 1))
    if "\x00" in text:
        raise MdlSyntaxError(
            "file contains a NUL byte (is it a binary file?)", SourceSpan.at_offset(path, text, text.index("\x00"))
        )
    surrogate = _SURROGATE.search(text)
    if surrogate is not None:  # only a str made in Python holds one: a file is decoded strictly
        remember_source(path, _SURROGATE.sub("\ufffd", text))  # the line shown must be printable
        raise MdlSyntaxError(
            f"the text holds U+{ord(surrogate.group()):04X}, a lone surrogate, which is not Unicode text "
            "(was it decoded with errors='surrogateescape'?)",
            SourceSpan.at_offset(path, text, surrogate.start()),
        )
    _check_nesting(text, path)
    from mbcal.language.syntax import statements  # Lark: only for a text not parsed before

    return statements(text, path)


# Bump when what is stored changes.
_ENTRY_VERSION = 1
# The parsed-model cache keeps at most this many entries (each a few kilobytes): writing one more
# removes the oldest down to _SYNTAX_KEEP.
_SYNTAX_ENTRIES, _SYNTAX_KEEP = 256, 192


@functools.lru_cache(maxsize=1)
def _syntax_code() -> bytes:
    """What the parsed statements depend on besides the text: the grammar, the modules that build
    and define them (this one, :mod:`~mbcal.language.syntax`, :mod:`~mbcal.language.ast`,
    :mod:`mbcal.errors`), Lark's install (its ``__init__``'s location, size and time: found
    without importing it) and Python's version."""
    from mbcal import __version__

    h = Hasher().add("syntax", _ENTRY_VERSION, sys.version, __version__)
    here = Path(__file__).parent
    for path in (grammar_path(), here / "parse.py", here / "syntax.py", here / "ast.py", Path(_errors.__file__)):
        h.add_file(path)  # an install whose files cannot be read (a zip) is keyed by the version
    spec = importlib.util.find_spec("lark")
    if spec is not None and spec.origin is not None:
        try:
            st = os.stat(spec.origin)
            h.add(spec.origin, st.st_size, st.st_mtime_ns)
        except OSError:  # Lark from a zip or a frozen bundle: its location only
            h.add(spec.origin)
    return h.hexdigest().encode()


def parse_text_cached(text: str, path: str) -> tuple[ast.Statement, ...]:
    """:func:`parse_text` through the parsed-model cache (none when caching is off): for the text of
    a file (a string parsed once, as in a test, gains nothing from it)."""
    folder = cache_dir()
    if folder is None or source_edited():  # the parser's code hashed in the key may not be what runs
        return parse_text(text, path)
    entry = folder / "syntax" / f"{Hasher().add(_syntax_code(), path, text).hexdigest()}.json"
    try:
        data = entry.read_bytes()
    except OSError:
        data = None
    if data is not None:
        try:
            with deep_recursion():
                stored = _from_json(json.loads(data))
        except (ValueError, TypeError, KeyError, RecursionError):  # truncated or foreign: parse again
            stored = None
        if isinstance(stored, tuple) and all(isinstance(s, ast.Statement) for s in stored):
            remember_source(path, text)  # for the messages of later checks, as a parse would
            with contextlib.suppress(OSError):
                os.utime(entry)  # used now: the last to be removed when the part is full
            return stored
    statements = parse_text(text, path)  # raises on an error: only a text that parsed is kept
    if source_edited(exact=True):  # the parser's modules, imported while it parsed, count too
        return statements
    try:
        with deep_recursion():
            data = json.dumps(_to_json(statements), separators=(",", ":")).encode()
        entry.parent.mkdir(parents=True, exist_ok=True)
        _make_room(entry.parent)
        atomic_write(entry, data, at_once=True)
    except (OSError, ValueError, TypeError, RecursionError):
        pass  # a read-only cache: still correct, only slower next time
    return statements


# The classes a stored syntax tree may name: the nodes of :mod:`ast` and SourceSpan, nothing else
# (an entry is data, never code: a name outside these is a foreign entry, parsed again).
_NODES: dict[str, type] = {
    name: cls for name, cls in vars(ast).items() if isinstance(cls, type) and dataclasses.is_dataclass(cls)
}
_NODES["SourceSpan"] = SourceSpan


def _to_json(value: object) -> object:
    """A syntax tree as JSON: a node as ``{"@": class, field: value, ...}``, a tuple as a list
    (the tree holds tuples only), numbers, strings, booleans and None as they are."""
    if isinstance(value, tuple):
        return [_to_json(v) for v in value]
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        if _NODES.get(type(value).__name__) is not type(value):
            raise TypeError(f"not a syntax-tree node: {type(value).__name__}")
        out: dict[str, object] = {"@": type(value).__name__}
        for f in dataclasses.fields(value):
            out[f.name] = _to_json(getattr(value, f.name))
        return out
    if value is None or isinstance(value, (str, int, float)):
        return value
    raise TypeError(f"cannot store {type(value).__name__} in a syntax tree")


def _from_json(value: object) -> object:
    """The syntax tree :func:`_to_json` wrote (ValueError, TypeError or KeyError: not one)."""
    if isinstance(value, list):
        return tuple(_from_json(v) for v in value)
    if isinstance(value, dict):
        cls = _NODES[value["@"]]
        names = {f.name for f in dataclasses.fields(cls)}
        if set(value) - {"@"} != names:
            raise ValueError(f"stored {cls.__name__} has other fields")
        return cls(**{name: _from_json(v) for name, v in value.items() if name != "@"})
    return value


def _make_room(folder: Path) -> None:
    """Remove the least recently used entries of the parsed-model cache when it holds
    :data:`_SYNTAX_ENTRIES`."""
    name = re.compile(CACHE_PARTS["syntax"][1])  # only the entries (the folder may hold the user's files)
    entries = [p for p in folder.iterdir() if name.fullmatch(p.name)]
    if len(entries) < _SYNTAX_ENTRIES:
        return

    def age(p: Path) -> float:
        try:
            return p.stat().st_mtime
        except OSError:
            return 0.0

    for old in sorted(entries, key=age)[: len(entries) - _SYNTAX_KEEP]:
        with contextlib.suppress(OSError):
            old.unlink()


def parse_text_with_includes(text: str, path: str = "<string>") -> tuple[ast.Statement, ...]:
    """Parse model text and the files it includes; includes resolve relative to ``path``
    (the current folder for ``"<string>"``)."""
    statements = parse_text(text, path)
    base = Path(path).resolve() if path != "<string>" else Path.cwd() / "<string>"
    return _resolve_includes(statements, base, (base,))


def _read_model_text(path: Path, span: SourceSpan | None) -> str:
    try:
        data = files.read_bytes(path)
    except FileNotFoundError:
        raise IncludeError(f"file not found: {path}", span) from None
    except IsADirectoryError:
        raise IncludeError(f"{path} is a directory, not a model file", span) from None
    except OSError as err:
        raise IncludeError(f"cannot read {path}: {err.strerror}", span) from None
    try:
        return data.decode("utf-8-sig")  # a byte-order mark (some Windows editors write one) is not text
    except UnicodeDecodeError as err:
        where = undecodable_at(display_path(path), err)
        raise IncludeError(f"not UTF-8 text (byte {err.start + 1}); is it a binary file?", where) from None


def parse_file(path: str | os.PathLike[str]) -> tuple[ast.Statement, ...]:
    """Parse a model file and, recursively, every file it includes.

    Each :class:`~mbcal.language.ast.Include` in the result carries the statements of the
    included file.  Include paths are relative to the including file.

    Raises
    ------
    IncludeError
        A file is missing or unreadable, or an include cycle is found (the message lists it).
    MdlSyntaxError
        In the file where the syntax error is.
    """
    return _parse_with_includes(Path(path), (), None)


def display_path(path: Path) -> str:
    """How a model file is named in messages and spans: relative to the working folder when it is
    below it, else as given."""
    try:
        rel = os.path.relpath(path)
    except ValueError:  # another drive on Windows
        return str(path)
    return rel if not rel.startswith("..") else str(path)


def _parse_with_includes(path: Path, stack: tuple[Path, ...], span: SourceSpan | None) -> tuple[ast.Statement, ...]:
    resolved = path.resolve()
    if resolved in stack:
        cycle = " -> ".join(display_path(p) for p in (*stack[stack.index(resolved) :], resolved))
        raise IncludeError(f"include cycle: {cycle}", span)
    if len(stack) >= MAX_INCLUDE_DEPTH:
        raise IncludeError(f"includes nested deeper than {MAX_INCLUDE_DEPTH} files", span)
    display = display_path(path) if span is None else display_path(resolved)
    text = _read_model_text(path, span)
    statements = parse_text_cached(text, display)
    return _resolve_includes(statements, resolved, (*stack, resolved))


def _resolve_includes(
    statements: tuple[ast.Statement, ...], current: Path, stack: tuple[Path, ...]
) -> tuple[ast.Statement, ...]:
    out: list[ast.Statement] = []
    for stmt in statements:
        if isinstance(stmt, ast.Include):
            target = current.parent / stmt.path
            body = _parse_with_includes(target, stack, stmt.span)
            stmt = ast.Include(span=stmt.span, path=stmt.path, resolved=str(target.resolve()), statements=body)
        elif isinstance(stmt, (ast.Frame, ast.Instance, ast.Template)):
            body = _resolve_includes(stmt.body, current, stack)
            stmt = _replace_body(stmt, body)
        out.append(stmt)
    return tuple(out)


def _replace_body(stmt, body):
    return dataclasses.replace(stmt, body=body)
