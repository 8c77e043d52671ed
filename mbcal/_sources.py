"""What mbcal's own source files were when mbcal was imported.

A compiled program saved to the cache (:mod:`mbcal.cache`) is keyed by a hash of mbcal's source
(:func:`mbcal.cache.code_fingerprint`), read when a process first asks for it.  A file saved
after mbcal was imported (a developer's edit in a running notebook, ``pip install -U`` under a
long process) is not the code that runs: that hash would file the old code's programs under the
new code's name (and a module imported after such a save runs code the hash never read).
mbcal's package ``__init__`` records here each source file's modification time and size (stat
calls only: ~1 ms, no file read), and :func:`mbcal.cache.source_edited` asks :func:`changed`
before programs or parsed files are loaded from the cache or saved to it.  Standard library only:
imported by ``import mbcal``.
"""

from __future__ import annotations

import os

_ROOT = os.path.dirname(os.path.abspath(__file__))


def stats() -> dict[str, tuple[int, int]]:
    """(modification time in ns, size) of every module of the package and of the grammar, by path."""
    out: dict[str, tuple[int, int]] = {}
    for folder, subfolders, files in os.walk(_ROOT):
        subfolders[:] = sorted(d for d in subfolders if d != "__pycache__")
        for name in files:
            if name.endswith((".py", ".lark")):
                _note(out, os.path.join(folder, name))
    _note(out, os.path.join(os.path.dirname(_ROOT), "grammar", "mdl.lark"))  # a source checkout's grammar
    return out


def _note(out: dict[str, tuple[int, int]], path: str) -> None:
    try:
        st = os.stat(path)
    except OSError:  # not there (a wheel has no checkout grammar) or gone
        return
    out[path] = (st.st_mtime_ns, st.st_size)


AT_IMPORT = stats()


def changed() -> bool:
    """Whether any of mbcal's source files was saved, added or removed since mbcal was imported."""
    return stats() != AT_IMPORT
