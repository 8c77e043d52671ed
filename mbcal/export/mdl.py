"""Write a calibrated model: the seed's environment model manager.

The output is the input model's text with the estimated values as nominal values.  A parameter
declared once in the main file, or overridden there, gets its value edited in place (its unit
kept); one declared in an included file, in a template (one statement, several instances) or in
an index range, or overridden in an included file, is set by an ``override`` statement appended
at the end (an override in the including file replaces one in a file it includes; the appended
one restates the prior σ the model had, which it replaces too).  Every relative file name in
the text (includes, meshes, ``points(...)`` targets) is rewritten to name the same file from
the output's folder.  The input file is never modified; the output is written atomically.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from mbcal.errors import MbcalError, MdlError, OutputError, SourceSpan
from mbcal.export.urdf import write_urdf
from mbcal.language import ast
from mbcal.language.check import check_at_nominal
from mbcal.language.model import Model
from mbcal.language.parse import display_path, parse_text_cached
from mbcal.language.urdf import urdf_to_mdl
from mbcal.outputs import atomic_write, check_output
from mbcal.units import UNITS

__all__ = ["write_calibrated_model", "format_value"]


def format_value(value: float, unit: str | None) -> str:
    """A value (SI) written in ``unit`` with enough digits to survive a round trip."""
    if unit is None:
        return repr(float(value)) if abs(value) >= 1e-4 or value == 0 else f"{value:.17g}"
    factor = UNITS[unit][0]
    v = value / factor
    text = f"{v:.12g}"
    return f"{text} {unit}"


def _offset(lines: list[str], line: int, column: int) -> int:
    return sum(len(lines[i]) for i in range(line - 1)) + column - 1


def _file_references(statements: Sequence[ast.Statement]) -> list[tuple[str, SourceSpan, str]]:
    """Every file name in a syntax tree, with its span and what names it (``include`` or
    ``string``).

    The language's strings are file names only (an include's, a mesh's, a ``points(...)``
    target's; a string anywhere else is an error), each relative to the file it is written in,
    so every string literal of the tree is one, wherever it stands.
    """
    found: list[tuple[str, SourceSpan, str]] = []

    def visit(node: object) -> None:
        if isinstance(node, ast.String):
            found.append((node.value, node.span, "string"))
        elif isinstance(node, ast.Include):
            found.append((node.path, node.span, "include"))  # the statements of the file are its own
        elif isinstance(node, tuple):
            for item in node:
                visit(item)
        elif isinstance(node, (ast.Expr, ast.Statement, ast.Keyword, ast.TemplateParam)):
            for f in dataclasses.fields(node):
                visit(getattr(node, f.name))

    with ast.deep_recursion():
        visit(tuple(statements))
    return found


def _relocate(text: str, source: Path, out: Path) -> list[tuple[int, int, str]]:
    """Edits that keep relative file names (includes, meshes, point files) valid from the output's folder."""
    if source.resolve().parent == out.resolve().parent:
        return []
    lines = text.splitlines(keepends=True)
    edits: list[tuple[int, int, str]] = []
    for value, span, what in _file_references(parse_text_cached(text, display_path(source))):
        if Path(value).is_absolute():
            continue
        target = (source.resolve().parent / value).resolve()
        try:
            new = os.path.relpath(target, out.resolve().parent)
        except ValueError:  # another drive
            new = str(target)
        # The parser sets end_line and end_column on every span it makes.
        assert span.end_line is not None and span.end_column is not None
        start = _offset(lines, span.line, span.column)
        end = _offset(lines, span.end_line, span.end_column)
        if what == "include":
            # The span is the whole statement: replace the string literal inside it.
            stmt = text[start:end]
            start, end = start + stmt.index('"'), start + len(stmt.rstrip())
        edits.append((start, end, json.dumps(new, ensure_ascii=False)))
    return edits


def _check_estimate(model: Model, values: Mapping[str, float], path) -> None:
    """The values must make a model that mbcal reads: within each parameter's hard limits, and
    sizes and focal lengths positive, camera settings, poses and points finite with them — the
    loader's own checks (:func:`~mbcal.language.check.check_at_nominal`), which apply to the
    nominal values that the written file declares.  A search range that includes f ≤ 0 let a fit
    find a mirror camera (f < 0), and the model written from it was refused by ``mbcal check``.

    Raises
    ------
    OutputError
        At the model's statement that the values make invalid, naming the file not written.
    """
    estimates = {name: value for name, value in values.items() if "@" not in name}  # not model values
    X = model.nominal.copy()
    for name, value in estimates.items():
        info = model.param(name)
        outside = info.outside_limits(value)
        if outside:
            raise OutputError(f"not writing {path}: the estimate {outside}", info.span)
        X[model.param_index(name)] = value
    try:
        check_at_nominal(model, X, where="with the estimated values")
    except MdlError as err:
        # The estimates that break it alone are named (the message names the model's setting).
        culprits = []
        for name, value in list(estimates.items())[:200]:  # an error's path only, bounded
            alone = model.nominal.copy()
            alone[model.param_index(name)] = value
            try:
                check_at_nominal(model, alone)
            except MdlError:
                info = model.param(name)
                culprits.append(f"{name} = {info.display(value):.6g}{f' {info.unit}' if info.unit else ''}")
        cause = f" (the estimate {', '.join(culprits)})" if culprits else ""
        raise OutputError(
            f"not writing {path}: {err.message}{cause}",
            err.span,
            hint="mbcal would refuse to read that model; limits [lo, hi] on a parameter keep its estimate valid "
            "(a focal length: limits [1, 1e6])",
        ) from None


def _unchanged_text(model: Model, source: Path, path) -> str:
    """The model file's text, as it was when the model was read: the estimates go in at the
    places the parser found their values, so a file saved since (a line added above) would have
    them land in other parameters' lines, or break the syntax, without a word."""
    data = source.read_bytes()
    recorded = dict(model.file_digests).get(model.path)
    if recorded and hashlib.sha256(data).hexdigest() != recorded:
        raise OutputError(
            f"not writing {path}: {model.path} has changed since the model was read from it (the estimates' "
            "places in it are those of the text read)",
            SourceSpan(str(model.path), 1, 1),
            hint="load the model again (and solve again if its parameters changed)",
        )
    return source.read_text(encoding="utf-8")


def write_calibrated_model(
    model: Model,
    values: Mapping[str, float],
    path,
    *,
    std: Mapping[str, float] | None = None,
    note: Sequence[str] = (),
    overwrite: bool = True,
    at_bound: Mapping[str, str] | None = None,
) -> None:
    """Write ``model`` with ``values`` (SI, by unknown name) as its nominal values (see module doc).

    Parameters
    ----------
    model : Model
        The model the values belong to; it must have been read from a file.
    values : mapping
        Estimates by parameter name; per-configuration copies (``name@config``) are listed in
        the header only.
    path : path
        The output (never one of the model's own files).
    std : mapping, optional
        σ of each value, for the header.
    note : sequence of str
        Extra header lines (what the values were estimated from).
    overwrite : bool
        Replace ``path`` if it exists.
    at_bound : mapping, optional
        Unknowns held at a hard limit (name → ``lower`` or ``upper``): the limit, not the data,
        gave their value, and the header says so instead of their σ of 0.

    Raises
    ------
    OutputError
        When the values make a model mbcal would refuse to read (a focal length ≤ 0, a size ≤ 0,
        a value outside its hard limits): nothing is written.
    """
    _check_estimate(model, values, path)
    source = Path(model.path)
    if source.suffix.lower() == ".urdf":
        _write_from_urdf(model, values, source, Path(path), overwrite=overwrite)
        return
    if not source.is_file():
        raise MbcalError(f"cannot write a calibrated model: the model was not read from a file ({model.path})")
    out = check_output(path, [model.path, *model.files, *model.data_files], overwrite=overwrite)
    text = model.source_text if model.source_text is not None else _unchanged_text(model, source, path)
    lines = text.splitlines(keepends=True)
    edits: list[tuple[int, int, str]] = []
    overrides: list[str] = []
    main = source.resolve()
    std = dict(std or {})
    held = dict(at_bound or {})
    for name, value in values.items():
        if "@" in name:
            continue  # per-configuration copies are not model values
        info = model.param(name)
        unit = info.value_unit
        new = format_value(value, unit)
        span = info.value_span
        in_place = (
            info.editable and span is not None and span.end_line is not None and Path(span.path).resolve() == main
        )
        if in_place:
            # in_place checked the span; the parser sets end_line and end_column together
            assert span is not None and span.end_line is not None and span.end_column is not None
            start = _offset(lines, span.line, span.column)
            end = _offset(lines, span.end_line, span.end_column)
            edits.append((start, end, new))
        elif info.overridden and info.sigma is not None:
            # It replaces an override in an included file, and with it that one's prior σ.
            overrides.append(f"override {name} = {new} sigma {format_value(info.sigma, unit)}")
        else:
            overrides.append(f"override {name} = {new}")
    edits.extend(_relocate(text, source, out))
    for start, end, new in sorted(edits, reverse=True):
        text = text[:start] + new + text[end:]
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    header = [f"# Calibrated by mbcal on {stamp} from {source.name}"]
    header.extend(f"# {line}" for line in note)
    for name, value in values.items():
        unit = model.param(name.split("@")[0]).unit
        s = std.get(name, float("nan"))
        shown = np.degrees(value) if unit == "deg" else value
        if name in held:
            sigma = f"held at its {held[name]} limit"
        elif np.isnan(s):
            sigma = "σ not given"
        elif not np.isfinite(s):
            sigma = "unobservable"
        else:
            sigma = f"σ {np.degrees(s) if unit == 'deg' else s:.3g}"
        header.append(f"#   {name} = {shown:.9g} {unit} ({sigma})".rstrip())
    body = "\n".join(header) + "\n\n" + text
    if overrides:
        if not body.endswith("\n"):
            body += "\n"
        body += (
            "\n# Calibrated values of parameters declared elsewhere (includes, templates, index ranges)"
            " or overridden in an included file:\n"
        )
        body += "\n".join(overrides) + "\n"
    atomic_write(out, body)


def _write_from_urdf(model: Model, values: Mapping[str, float], source: Path, out: Path, *, overwrite: bool) -> None:
    """A model read from a URDF: a calibrated URDF (offsets folded into the joint origins), or
    the model as .mdl text with the estimates as ``override`` statements."""
    if out.suffix.lower() == ".urdf":
        write_urdf(values, source, out, overwrite=overwrite)
        return
    check_output(out, [source], overwrite=overwrite)
    text = urdf_to_mdl(source, mesh_base=out.resolve().parent)
    lines = [f"# Calibrated by mbcal from {source.name}: estimates as overrides of the URDF's values", ""]
    for name, value in values.items():
        if "@" in name:
            continue
        info = model.param(name)
        lines.append(f"override {name} = {format_value(value, 'deg' if info.unit == 'deg' else None)}")
    atomic_write(out, text.rstrip("\n") + "\n\n" + "\n".join(lines) + "\n")
