"""Loading a model: a .mdl file (with its includes and meshes) or a URDF robot, checked into a
:class:`~mbcal.language.model.Model`."""

from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path

from mbcal.errors import MdlError, SourceSpan
from mbcal.language import files as _files
from mbcal.language.check import check
from mbcal.language.model import Model
from mbcal.language.parse import deep_recursion, parse_file, parse_text_with_includes
from mbcal.language.urdf import urdf_to_mdl

__all__ = ["load_model", "load_model_text", "load_urdf"]


def _too_deep(path: str) -> MdlError:
    return MdlError(
        "the model's definitions nest too deeply (lets or templates in long chains)", SourceSpan(path, 1, 1)
    )


def _read_digests(model: Model, read: dict[str, str]) -> Model:
    """The model with the digests of the files it was read from (:attr:`Model.file_digests`): of
    the bytes read (``read``, :func:`mbcal.language.files.recording`), else (a file its reader
    hands to another library: a .gltf's buffers) as the file is now."""
    digests = []
    for name in dict.fromkeys([*model.files, *model.data_files]):
        digest = _files.digest_of(read, name)
        if digest is None:
            try:
                digest = hashlib.sha256(Path(name).read_bytes()).hexdigest()
            except OSError:
                digest = ""
        digests.append((name, digest))
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
    with _files.recording() as read:
        try:
            statements = parse_file(path)
            with deep_recursion():
                model = check(statements, str(path))
        except RecursionError:
            raise _too_deep(str(path)) from None
    return _read_digests(model, read)


def load_model_text(text: str, path: str = "<string>") -> Model:
    """Parse and check model text; includes and meshes resolve relative to ``path``."""
    if not isinstance(text, str):
        raise MdlError(
            f"model text must be a str, got {type(text).__name__}"
            + (" (decode it first)" if isinstance(text, bytes) else "")
        )
    with _files.recording() as read:
        model = _checked_text(text, path)
    return _read_digests(model, read)


def _checked_text(text: str, path: str) -> Model:
    try:
        statements = parse_text_with_includes(text, path)
        with deep_recursion():
            model = check(statements, path)
    except RecursionError:
        raise _too_deep(path) from None
    # The text is not in a file the cache could hash: its digest stands for it.
    return dataclasses.replace(model, text_digest=hashlib.sha256(text.encode("utf-8")).hexdigest(), source_text=text)


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
    with _files.recording() as read:
        text = urdf_to_mdl(path)
        model = _checked_text(text, str(path.with_name(path.name + ".mdl")))  # digests once, below
    return _read_digests(dataclasses.replace(model, path=str(path), files=(str(path), *model.files[1:])), read)
