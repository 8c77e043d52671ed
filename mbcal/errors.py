"""One error hierarchy for everything a user can get wrong.

Every error a user can cause is an :class:`MbcalError`.  Errors that point into a file carry
a :class:`SourceSpan`; ``str(error)`` is then ``path:line:col: message`` and
:meth:`MbcalError.render` adds the offending source line with a caret under the column.
The command line prints ``render()`` and exits with status 2 — never a traceback.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "SourceSpan",
    "MbcalError",
    "MdlError",
    "MdlSyntaxError",
    "UndefinedNameError",
    "DuplicateNameError",
    "IncludeError",
    "UnitError",
    "MdlTypeError",
    "ArgumentError",
    "DimensionError",
    "MeshError",
    "ParameterError",
    "UnknownNameError",
    "MeasurementFileError",
    "SolverError",
    "UrdfError",
    "OutputError",
    "RenderError",
    "KinematicsError",
    "UnreachableError",
    "MbcalWarning",
    "MeasurementFileWarning",
    "suggest",
    "shown",
    "undecodable_at",
    "remember_source",
]

# Text of every file the parser has read, so an error can show its line even when the file
# changed on disk afterwards (or never existed, as for strings parsed in tests).
_SOURCES: dict[str, str] = {}


def remember_source(path: str, text: str) -> None:
    """Keep ``text`` as the content of ``path`` for error messages."""
    _SOURCES[path] = text


def _source_line(path: str, line: int) -> str | None:
    text = _SOURCES.get(path)
    if text is None:
        try:
            text = Path(path).read_text(encoding="utf-8", errors="replace")
        except OSError:
            return None
    lines = text.splitlines()
    if 1 <= line <= len(lines):
        return lines[line - 1]
    return None


@dataclass(frozen=True)
class SourceSpan:
    """Where something stands in a source file (1-based line and column)."""

    path: str
    line: int
    column: int
    end_line: int | None = None
    end_column: int | None = None

    def __str__(self) -> str:
        return f"{self.path}:{self.line}:{self.column}"

    @staticmethod
    def at_offset(path: str, text: str, offset: int) -> SourceSpan:
        """The line and column of character ``offset`` of ``text`` (lines end at ``\\n``)."""
        return SourceSpan(path, text.count("\n", 0, offset) + 1, offset - (text.rfind("\n", 0, offset) + 1) + 1)


class MbcalError(Exception):
    """Base of every error a user of mbcal can cause.

    Parameters
    ----------
    message : str
        What is wrong, in the user's terms.
    span : SourceSpan, optional
        Where it is wrong.
    hint : str, optional
        What would fix it; printed on a line of its own.
    """

    exit_code = 2

    def __init__(self, message: str, span: SourceSpan | None = None, hint: str | None = None):
        # A name of 100,000 characters from a bad file is named, not echoed whole.
        self.message = _long_words_cut(message)
        self.span = span
        self.hint = None if hint is None else _long_words_cut(hint)
        super().__init__(str(self))

    def __str__(self) -> str:
        text = f"{self.span}: {self.message}" if self.span else self.message
        if self.hint:
            text += f" ({self.hint})"
        return text

    def render(self) -> str:
        """The message, the source line and a caret under the column, for a terminal."""
        head = f"{self.span}: {self.message}" if self.span else self.message
        lines = [head]
        if self.span is not None:
            source = _source_line(self.span.path, self.span.line)
            if source is not None:
                source = source.replace("\t", " ")
                column = self.span.column
                if len(source) > _SHOWN:  # a one-line JSON file of 40 kB: the part around the column
                    start = max(0, min(column - 1 - _SHOWN // 2, len(source) - _SHOWN))
                    source = (
                        ("…" if start else "")
                        + source[start : start + _SHOWN]
                        + ("…" if start + _SHOWN < len(source) else "")
                    )
                    column -= start - (1 if start else 0)
                lines.append(f"    {source}")
                width = 1
                if self.span.end_line == self.span.line and self.span.end_column:
                    width = max(1, self.span.end_column - self.span.column)
                lines.append("    " + " " * (column - 1) + "^" * min(width, 60))
        if self.hint:
            lines.append(f"hint: {self.hint}")
        return "\n".join(lines)


_SHOWN = 160
"""The most characters of a source line an error shows (around its column)."""


class MdlError(MbcalError):
    """An error in a model description (.mdl or .urdf)."""


class MdlSyntaxError(MdlError):
    """The text does not follow the grammar."""


class UndefinedNameError(MdlError):
    """A name is used that nothing declares."""


class DuplicateNameError(MdlError):
    """The same name is declared twice in one scope."""


class IncludeError(MdlError):
    """An include is missing, unreadable, or part of a cycle."""


class UnitError(MdlError):
    """A quantity has the wrong unit (an angle where a length is expected, ...)."""


class MdlTypeError(MdlError):
    """A value has the wrong shape (a vector where a number is expected, ...)."""


class ArgumentError(MdlError):
    """A call has too many, too few or unknown arguments."""


class DimensionError(MdlError):
    """A shape dimension is negative or otherwise impossible."""


class MeshError(MdlError):
    """A mesh file is missing, empty or unreadable."""


class ParameterError(MbcalError):
    """A parameter selection or value names something the model does not have."""


class UnknownNameError(ParameterError):
    """A frame, point, sensor or shape name that the model does not have (or that is ambiguous)."""


class MeasurementFileError(MbcalError):
    """A measurement or plan file is malformed.  ``field``: the column (CSV) or key (JSON) the
    error is about, when it is about one: a CSV reader points at that cell."""

    def __init__(self, message: str, span: SourceSpan | None = None, hint: str | None = None, field: str | None = None):
        self.field = field
        super().__init__(message, span, hint)


class SolverError(MbcalError):
    """A problem cannot be set up for the solver (e.g. no unknowns)."""


class MeasurementModelError(MbcalError):
    """A measurement model (a plugin) broke its protocol: ``predict`` or ``visible`` gave an array
    of the wrong shape, or one of its methods raised (the original error is the ``__cause__``)."""


class UrdfError(MdlError):
    """A URDF file cannot be read or turned into a model."""


class OutputError(MbcalError):
    """An output cannot be written (it would overwrite an input, its folder is missing, ...)."""


class RenderError(MbcalError):
    """Headless rendering is not available (no EGL/OSMesa) or failed."""


class KinematicsError(MbcalError):
    """A kinematic chain cannot be set up or evaluated (a joint that does not move the target, a
    joint vector of the wrong length, ...)."""


class UnreachableError(KinematicsError):
    """Inverse kinematics found no joint values within the tolerance: the message names each target
    out of reach, the closest pose found and its distance."""

    exit_code = 1


class MbcalWarning(UserWarning):
    """Base of the warnings mbcal gives about a user's input or set-up: something read or done as
    asked that is probably not what was meant.  The command line prints them as
    ``warning: MESSAGE`` on standard error."""


class MeasurementFileWarning(MbcalWarning):
    """A measurement file read as written but probably wrong (a row pasted twice); the message
    starts with ``file:line:``."""


def undecodable_at(path: str, err: UnicodeDecodeError, first_line: int = 1) -> SourceSpan:
    """Where the first byte that is not UTF-8 lies in the text ``err`` failed on (its line counted
    from ``first_line``): the column in characters, as an editor shows it, not in bytes."""
    # Lines end at LF, CR LF or a lone CR (old Mac files), as an editor counts them.
    before = err.object[: err.start].replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    line_start = before.rfind(b"\n") + 1
    column = len(before[line_start:].decode("utf-8", errors="replace")) + 1
    return SourceSpan(path, first_line + before.count(b"\n"), column)


def _cut(text: str, limit: int) -> str:
    """``text``, cut in the middle when longer than ``limit`` characters, with its length."""
    if len(text) <= limit:
        return text
    half = (limit - 1) // 2
    return f"{text[:half]}…{text[-half:]} ({len(text):,} characters)"


def shown(value: object, limit: int = 60) -> str:
    """``repr(value)`` for a message, cut in the middle when longer than ``limit`` characters: a
    bad value of 100,000 characters is named, not echoed in full."""
    return _cut(repr(value), limit)


_LONGEST_WORD = 1024
"""The most characters of one word (a run without white space: a name, a path) an error message
repeats; a longer one is cut in the middle (paths run to a few hundred characters at most on
real machines: they stay whole)."""
_LONG_WORD = re.compile(r"\S{" + str(_LONGEST_WORD + 1) + ",}")


def _long_words_cut(text: str) -> str:
    if len(text) <= _LONGEST_WORD:
        return text
    return _LONG_WORD.sub(lambda m: _cut(m.group(0), 161), text)


def suggest(name: str, candidates: Iterable[str], n: int = 3) -> str | None:
    """A ``did you mean ...?`` hint listing close matches of ``name``, or None."""
    pool = sorted(set(candidates))
    close = difflib.get_close_matches(name, pool, n=n, cutoff=0.6)
    if not close:
        # Compare with the same number of trailing components: 'lever.tpi' vs 'room.valve.lever.tip'.
        k = name.count(".") + 1
        tails: dict[str, list[str]] = {}
        for c in pool:
            tails.setdefault(".".join(c.split(".")[-k:]), []).append(c)
        for tail in difflib.get_close_matches(name, list(tails), n=n, cutoff=0.6):
            close.extend(tails[tail])
        close = close[:n]
    if not close:
        return None
    return "did you mean " + ", ".join(f"'{c}'" for c in close) + "?"
