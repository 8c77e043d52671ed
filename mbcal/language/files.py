"""The files a model is read from, and the digests of the bytes read (for the compiled-program
cache: a problem is keyed by the content its model was built from, not by the files as they are
when the problem is built, nor as they are at the end of the load)."""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path

__all__ = ["digest_of", "note", "read_bytes", "recording"]

_DIGESTS: ContextVar[dict[str, str] | None] = ContextVar("mbcal_model_file_digests", default=None)


def _key(path: str | os.PathLike[str]) -> str:
    return os.path.realpath(path)


@contextlib.contextmanager
def recording() -> Iterator[dict[str, str]]:
    """Collect, while inside, the SHA-256 of the first bytes read of every file (by its real path);
    a load inside another adds to the outer one's."""
    outer = _DIGESTS.get()
    digests: dict[str, str] = {} if outer is None else outer
    token = _DIGESTS.set(digests)
    try:
        yield digests
    finally:
        _DIGESTS.reset(token)


def note(path: str | os.PathLike[str], data: bytes) -> None:
    """Record the digest of ``data`` as read from ``path`` (the first read of a file counts)."""
    digests = _DIGESTS.get()
    if digests is not None:
        digests.setdefault(_key(path), hashlib.sha256(data).hexdigest())


def read_bytes(path: str | os.PathLike[str]) -> bytes:
    """``Path(path).read_bytes()``, recorded (:func:`note`)."""
    data = Path(path).read_bytes()
    note(path, data)
    return data


def digest_of(digests: dict[str, str], path: str | os.PathLike[str]) -> str | None:
    """The recorded digest of ``path``, or None."""
    return digests.get(_key(path))
