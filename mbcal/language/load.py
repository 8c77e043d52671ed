"""Loading a model: a .mdl file (with its includes and meshes) or a URDF robot, checked into a
:class:`~mbcal.language.model.Model`."""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

from mbcal.errors import MdlError, SourceSpan
from mbcal.language.check import check
from mbcal.language.model import Model
from mbcal.language.parse import deep_recursion, parse_file, parse_text_with_includes
from mbcal.language.urdf import urdf_to_mdl

__all__ = ["load_model", "load_model_text", "load_urdf"]


def _too_deep(path: str) -> MdlError:
    return MdlError(
        "the model's definitions nest too deeply (lets or templates in long chains)", SourceSpan(path, 1, 1)
    )


def _read_digests(model: Model) -> Model:
    """The model with the digests of the files it was read from, as they are now, at the end of
    reading it (:attr:`Model.file_digests`)."""
    digests = []
    for name in dict.fromkeys([*model.files, *model.data_files]):
        try:
            digests.append((name, hashlib.sha256(Path(name).read_bytes()).hexdigest()))
        except OSError:
            digests.append((name, ""))
    return dataclasses.replace(model, file_digests=tuple(digests))


def load_model(path: str | os.PathLike[str]) -> Model:
    """Read, parse and check a model file (``.mdl``, or ``.urdf`` for robot descriptions).

    Raises
    ------
    MdlError
        Any error in the model (or a file it includes), with its location.
    """
    path = Path(path)
    if path.suffix.lower() == ".urdf":
        return load_urdf(path)
    try:
        statements = parse_file(path)
        with deep_recursion():
            model = check(statements, str(path))
    except RecursionError:
        raise _too_deep(str(path)) from None
    return _read_digests(model)


def load_model_text(text: str, path: str = "<string>") -> Model:
    """Parse and check model text; includes and meshes resolve relative to ``path``."""
    if not isinstance(text, str):
        raise MdlError(
            f"model text must be a str, got {type(text).__name__}"
            + (" (decode it first)" if isinstance(text, bytes) else "")
        )
    try:
        statements = parse_text_with_includes(text, path)
        with deep_recursion():
            model = check(statements, path)
    except RecursionError:
        raise _too_deep(path) from None
    # The text is not in a file the cache could hash: its digest stands for it.
    return _read_digests(dataclasses.replace(model, text_digest=hashlib.sha256(text.encode("utf-8")).hexdigest()))


def load_urdf(path: str | os.PathLike[str]) -> Model:
    """A URDF file as a checked model; ``model.path`` is the URDF's path.

    The generated text (:func:`urdf_to_mdl`) is checked as if it were a model file beside the
    URDF, so mesh paths resolve.

    Raises
    ------
    MdlError
        :class:`UrdfError` for a malformed URDF (file and line where known).
    """
    path = Path(path)
    text = urdf_to_mdl(path)
    model = load_model_text(text, str(path.with_name(path.name + ".mdl")))
    return _read_digests(dataclasses.replace(model, path=str(path), files=(str(path), *model.files[1:])))
