"""The model description language: parse (Lark → syntax tree), check (→ Model), IR."""

from __future__ import annotations

import os
from pathlib import Path

from mbcal.errors import MdlError, SourceSpan
from mbcal.language.check import check
from mbcal.language.model import Model
from mbcal.language.parse import deep_recursion, parse_file, parse_text

__all__ = ["load_model", "load_model_text", "Model"]


def load_model(path: str | os.PathLike[str]) -> Model:
    """Read, parse and check a model file (``.mdl``, or ``.urdf`` for robot descriptions).

    Raises
    ------
    MdlError
        Any error in the model (or a file it includes), with its location.
    """
    path = Path(path)
    if path.suffix.lower() == ".urdf":
        from mbcal.urdf import load_urdf

        return load_urdf(path)
    try:
        statements = parse_file(path)
        with deep_recursion():
            return check(statements, str(path))
    except RecursionError:
        raise MdlError(
            "the model's definitions nest too deeply (lets or templates in long chains)", SourceSpan(str(path), 1, 1)
        ) from None


def load_model_text(text: str, path: str = "<string>") -> Model:
    """Parse and check model text; includes and meshes resolve relative to ``path``."""
    from mbcal.language.parse import _resolve_includes

    try:
        statements = parse_text(text, path)
        base = Path(path).resolve() if path != "<string>" else Path.cwd() / "<string>"
        statements = _resolve_includes(statements, base, (base,))
        with deep_recursion():
            return check(statements, path)
    except RecursionError:
        raise MdlError(
            "the model's definitions nest too deeply (lets or templates in long chains)", SourceSpan(path, 1, 1)
        ) from None
