"""Write a calibrated model: the seed's environment model manager.

The output is the input model's text with the estimated values as nominal values.  A parameter
declared once in the main file gets its value edited in place (its unit kept); one declared in
an included file, in a template (one statement, several instances) or in an index range is
set by an ``override`` statement appended at the end.  The input file is never modified; the
output is written atomically.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mbcal.errors import MbcalError
from mbcal.units import UNITS

if TYPE_CHECKING:
    from mbcal.api import CalibrationResult

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


def _file_references(statements) -> list:
    """Every string literal naming a file (includes, meshes) in a syntax tree, with its span."""
    from mbcal.language import ast

    found = []
    for stmt in statements:
        if isinstance(stmt, ast.Include):
            found.append((stmt.path, stmt.span, "include"))
        elif isinstance(stmt, ast.Shape) and stmt.kind == "mesh":
            for arg in [*stmt.args[:1], *(k.value for k in stmt.kwargs if k.name == "file")]:
                if isinstance(arg, ast.String):
                    found.append((arg.value, arg.span, "mesh"))
        if isinstance(stmt, (ast.Frame, ast.Instance, ast.Template)):
            found.extend(_file_references(stmt.body))
    return found


def _relocate(text: str, source: Path, out: Path) -> list[tuple[int, int, str]]:
    """Edits that keep relative include and mesh paths valid from the output's folder."""
    import json
    import os

    from mbcal.language.parse import parse_text

    if source.resolve().parent == out.resolve().parent:
        return []
    lines = text.splitlines(keepends=True)
    edits = []
    for value, span, what in _file_references(parse_text(text, str(source))):
        if Path(value).is_absolute():
            continue
        target = (source.resolve().parent / value).resolve()
        try:
            new = os.path.relpath(target, out.resolve().parent)
        except ValueError:  # another drive
            new = str(target)
        if what == "include":
            # The span is the whole statement: replace the string literal inside it.
            start = _offset(lines, span.line, span.column)
            end = _offset(lines, span.end_line, span.end_column)
            stmt = text[start:end]
            q = stmt.index('"')
            edits.append((start + q, start + len(stmt.rstrip()), json.dumps(new, ensure_ascii=False)))
        else:
            edits.append(
                (
                    _offset(lines, span.line, span.column),
                    _offset(lines, span.end_line, span.end_column),
                    json.dumps(new, ensure_ascii=False),
                )
            )
    return edits


def write_calibrated_model(result: CalibrationResult, path, *, overwrite: bool = True) -> None:
    """Write ``result``'s model with the estimates as nominal values (see module doc)."""
    from mbcal.fileio import atomic_write, check_output

    model = result.problem.model
    source = Path(model.path)
    if source.suffix.lower() == ".urdf":
        _write_from_urdf(result, source, Path(path), overwrite=overwrite)
        return
    if not source.is_file():
        raise MbcalError(f"cannot write a calibrated model: the model was not read from a file ({model.path})")
    out = check_output(path, [model.path, *model.files], overwrite=overwrite)
    text = source.read_text(encoding="utf-8")
    lines = text.splitlines(keepends=True)
    edits: list[tuple[int, int, str]] = []
    overrides: list[str] = []
    main = source.resolve()
    values = result.values
    std = result.std
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
            start = _offset(lines, span.line, span.column)
            end = _offset(lines, span.end_line, span.end_column)
            edits.append((start, end, new))
        else:
            overrides.append(f"override {name} = {new}")
    edits.extend(_relocate(text, source, out))
    for start, end, new in sorted(edits, reverse=True):
        text = text[:start] + new + text[end:]
    stamp = _dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    header = [f"# Calibrated by mbcal on {stamp} from {source.name}"]
    if result.problem.measurements.path:
        header.append(
            f"# with {result.problem.measurements.path}: S = {result.cost:.6g}, "
            + ", ".join(f"RMS {k} {v:.4g}" for k, v in result.rms.items())
        )
    for name, value in values.items():
        unit = result.unit(name)
        s = std[name]
        shown = np.degrees(value) if unit == "deg" else value
        sigma = "unobservable" if not np.isfinite(s) else f"σ {np.degrees(s) if unit == 'deg' else s:.3g}"
        header.append(f"#   {name} = {shown:.9g} {unit} ({sigma})".rstrip())
    body = "\n".join(header) + "\n\n" + text
    if overrides:
        if not body.endswith("\n"):
            body += "\n"
        body += "\n# Calibrated values of parameters declared elsewhere (includes, templates, index ranges):\n"
        body += "\n".join(overrides) + "\n"
    atomic_write(out, body)


def _write_from_urdf(result, source: Path, out: Path, *, overwrite: bool) -> None:
    """A model read from a URDF: a calibrated URDF (offsets folded into the joint origins), or
    the model as .mdl text with the estimates as ``override`` statements."""
    from mbcal.fileio import atomic_write, check_output
    from mbcal.urdf import urdf_to_mdl, write_urdf

    if out.suffix.lower() == ".urdf":
        write_urdf(result, source, out, overwrite=overwrite)
        return
    check_output(out, [source], overwrite=overwrite)
    text = urdf_to_mdl(source, mesh_base=out.resolve().parent)
    lines = [f"# Calibrated by mbcal from {source.name}: estimates as overrides of the URDF's values", ""]
    for name, value in result.values.items():
        if "@" in name:
            continue
        info = result.problem.model.param(name)
        lines.append(f"override {name} = {format_value(value, 'deg' if info.unit == 'deg' else None)}")
    atomic_write(out, text.rstrip("\n") + "\n\n" + "\n".join(lines) + "\n")
