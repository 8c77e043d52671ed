"""Caches that make the second run of a problem start fast.

Five caches, all in ``$MBCAL_CACHE_DIR`` (default ``$XDG_CACHE_HOME/mbcal`` or
``~/.cache/mbcal``); ``MBCAL_CACHE=off`` turns them off:

* JAX's persistent compilation cache (``jax/``): compiled XLA executables, keyed by JAX on the
  program and the compiler — a compile becomes a file read.
* exported solver programs (``exports/``): the traced and lowered solver of a problem, saved
  with ``jax.export``.  Tracing a model through ``vmap``, ``jacfwd`` and the Marquardt loop takes
  about a second; a second process that solves the same problem (the same model files, meshes,
  measurement structure, unknowns, σ, solver settings, shapes and mbcal code — only the
  measured values and known readings may differ) loads the program instead and, with the
  compilation cache, gets its first result in a fraction of a second.
* the model language's parser tables (``lark/``, :mod:`mbcal.language.syntax`): Lark's LALR
  tables, checked by Lark against a hash of the grammar — every command starts ~0.1 s sooner.
* the triangles of mesh files (``meshes/``, :mod:`mbcal.language.meshes`): keyed by the file's
  bytes, its format and trimesh's version; a command on a model with meshes does not import
  trimesh (~0.6 s) to read them again (every format but ``.gltf``, whose buffers are other files).
* model files parsed (``syntax/``, :mod:`mbcal.language.parse`): a file's statements, keyed by
  its text and path, the grammar and the parser's code; a command on a model parsed before does
  not import Lark (~0.06 s with the parse).  The least recently used go beyond 256 entries.

``mbcal cache`` shows what each holds (:func:`cache_contents`) and ``mbcal cache --clear`` removes
it (:func:`clear_cache`; only files with the names these caches give them).  The two parts that
grow with every new problem structure — ``exports/`` and ``jax/`` — are each kept under
``MBCAL_CACHE_MAX_MB`` megabytes (default 256, :func:`max_part_bytes`): whenever mbcal saves a
new program, the least recently used entries beyond that go (:func:`trim_programs`).

This module imports JAX only when a JAX cache is used, so the parser (and ``mbcal check``) can
use :func:`cache_dir` without loading JAX.

Entries are keyed by content hashes, so a changed model, measurement plan or mbcal version never
reuses a stale program.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import math
import os
import re
import stat
import sys
import threading
import time
import warnings
import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mbcal import _sources
from mbcal._collector import gc_paused
from mbcal.errors import MbcalError, MbcalWarning
from mbcal.outputs import atomic_write
from mbcal.resources import find_bundled, package_root

__all__ = [
    "cache_dir",
    "cache_dir_problem",
    "CacheOffWarning",
    "cache_contents",
    "clear_cache",
    "Cleared",
    "max_part_bytes",
    "trim_programs",
    "CACHE_PARTS",
    "enable_compilation_cache",
    "exported",
    "code_fingerprint",
    "source_edited",
    "SourceEditedWarning",
    "Hasher",
    "ProgramCache",
    "PROGRAMS",
]


class ProgramCache:
    """A small least-recently-used cache of compiled programs, shared within one process.

    Objects of the same structure (two :class:`mbcal.problem.Problem` of one model and one
    measurement plan, differing only in the measured values) can run the same jitted functions:
    the second one then neither traces nor compiles.  The cache is *bounded*: every compiled XLA
    executable holds memory maps and code, and a process that keeps hundreds of them alive (a
    long test session) can exhaust the kernel's map limit and crash inside XLA's compiler.  When
    more than ``size`` entries exist the least recently used is dropped, and its programs are
    freed once nothing else refers to them.
    """

    def __init__(self, size: int):
        self.size = size
        self._entries: OrderedDict[Any, Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any, build: Callable[[], Any]) -> Any:
        """The entry for ``key``, built by ``build()`` on a miss (outside the lock: a build traces)."""
        with self._lock:
            if key in self._entries:
                self._entries.move_to_end(key)
                return self._entries[key]
        value = build()
        with self._lock:
            value = self._entries.setdefault(key, value)
            self._entries.move_to_end(key)
            while len(self._entries) > self.size:
                self._entries.popitem(last=False)
        return value

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()


# Programs of problems (mbcal.problem) and exported solver programs loaded from the cache folder.
# A few structures are plenty for a process that solves one problem again and again (a server,
# a Monte Carlo loop, a notebook); a test session that builds hundreds keeps only the latest.
PROGRAMS = ProgramCache(8)
_LOADED = ProgramCache(8)


def _configured_dir() -> Path | None:
    """The cache folder the environment names (None: MBCAL_CACHE=off), usable or not."""
    if os.environ.get("MBCAL_CACHE", "").lower() in ("0", "off", "no", "false"):
        return None
    if os.environ.get("MBCAL_CACHE_DIR"):
        return Path(os.environ["MBCAL_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mbcal"


def cache_dir_problem() -> str | None:
    """Why the cache folder the environment names cannot be one, or None: it (or the nearest of
    its parents that exists) is a file or something else that is not a folder.  A folder that
    merely cannot be written is not a problem here: the caches then run without writing, as
    before (an unwritable home)."""
    folder = _configured_dir()
    if folder is None:
        return None
    for path in (folder, *folder.parents):
        try:
            mode = path.stat().st_mode
        except (FileNotFoundError, NotADirectoryError):
            continue  # not there (yet): its parent says whether it can be made
        except OSError:
            return None  # unreadable: left to the caches, which run without it
        if stat.S_ISDIR(mode):
            return None
        named = "$MBCAL_CACHE_DIR" if os.environ.get("MBCAL_CACHE_DIR") else "the cache folder"
        if path == folder:
            return f"{named} ({folder}) is not a folder"
        return f"{named} ({folder}) is under {path}, which is not a folder"
    return None


class CacheOffWarning(MbcalWarning):
    """The cache folder cannot be one (a file): mbcal runs without its caches (:func:`cache_dir`)."""


_CACHE_OFF_SAID: set[str] = set()


def cache_dir() -> Path | None:
    """The cache folder, or None when caching is off: ``MBCAL_CACHE=off``, or a folder that is a
    file (or under one), which is said once per process as a :class:`CacheOffWarning`."""
    folder = _configured_dir()
    if folder is None:
        return None
    problem = cache_dir_problem()
    if problem is None:
        return folder
    if problem not in _CACHE_OFF_SAID:
        _CACHE_OFF_SAID.add(problem)
        warnings.warn(
            CacheOffWarning(
                f"the cache is off: {problem}; nothing is kept between runs, so each command starts slower "
                "(set MBCAL_CACHE_DIR to a folder, or MBCAL_CACHE=off to say so)"
            ),
            stacklevel=2,
        )
    return None


# The parts of the cache folder: what each holds and the names of the files written there (by
# mbcal, by JAX's compilation cache, by Lark for mbcal's grammar), with the leftovers of an
# interrupted atomic write (mbcal.outputs.atomic_write: ".NAME.XXXX.part").  `mbcal cache --clear`
# removes files with these names only: MBCAL_CACHE_DIR may name a folder that holds other files.
CACHE_PARTS: dict[str, tuple[str, str]] = {
    "exports": (
        "traced programs (jax.export) and their inputs' recipes: a later process does not trace them",
        r"[0-9a-f]{64}\.(?:jaxexport|recipe\.json)",
    ),
    # JAX names its entries "<module name>-<sha256>-cache", the module name with [^\w.-] replaced
    "jax": ("compiled programs (JAX's compilation cache)", r"[\w.\-]+-[0-9a-f]{64}-(?:cache|atime)"),
    "meshes": ("triangles of mesh files, keyed by their bytes", r"[0-9a-f]{64}\.npz"),
    "lark": ("the model language's parser tables", r"mdl-grammar\.lark"),
    "syntax": ("model files parsed, keyed by their text (at most 256)", r"[0-9a-f]{64}\.json"),
}


def _cache_files(folder: Path, part: str) -> list[tuple[Path, os.stat_result]]:
    """The files of one part of the cache folder that carry its names (nothing else: no link, no
    folder), with their stat, in name order: one scan of the folder, one stat per file (thousands
    of entries: ~30 ms).  An unreadable folder raises OSError; a missing one holds nothing."""
    name = re.compile(CACHE_PARTS[part][1])
    leftover = re.compile(r"\.(?:" + CACHE_PARTS[part][1] + r")\.[^/]+\.part")
    where = folder / part
    if not where.is_dir():
        return []
    found = []
    with os.scandir(where) as listing:
        for item in listing:
            if not (name.fullmatch(item.name) or leftover.fullmatch(item.name)):
                continue
            try:
                if item.is_file(follow_symlinks=False):
                    found.append((Path(item.path), item.stat(follow_symlinks=False)))
            except OSError:  # removed meanwhile
                continue
    return sorted(found, key=lambda file: file[0].name)


def _remove(path: Path, problems: list[str]) -> bool:
    """Remove one cached file: True when this call removed it; one that cannot be removed is said
    in ``problems``; one already gone (another process) is neither."""
    try:
        path.unlink()
    except FileNotFoundError:
        return False
    except OSError as err:
        problems.append(f"{path}: {err.strerror or err}")
        return False
    return True


def cache_contents(folder: Path | None = None) -> list[dict[str, Any]]:
    """Each part of the cache folder (``folder``, default :func:`cache_dir`): its name, what it
    holds, its folder, the number of files and their size in bytes, and ``error`` (the reason)
    for a part that could not be read; empty when caching is off."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return []
    out = []
    for part, (what, _) in CACHE_PARTS.items():
        entry: dict[str, Any] = {"part": part, "holds": what, "folder": str(folder / part), "files": 0, "bytes": 0}
        try:
            files = _cache_files(folder, part)
        except OSError as err:  # an unreadable folder: said, and the other parts still shown
            entry["error"] = f"{type(err).__name__}: {err.strerror or err}"
        else:
            entry.update(files=len(files), bytes=sum(st.st_size for _, st in files))
        out.append(entry)
    return out


@dataclass(frozen=True)
class Cleared:
    """What :func:`clear_cache` removed, and what it could not (``problems``: one line each)."""

    files: int
    bytes: int
    problems: tuple[str, ...] = ()


def clear_cache(folder: Path | None = None, parts: Sequence[str] | None = None) -> Cleared:
    """Remove the cached files (of ``parts``, default all) from the cache folder.  Only files with
    the names mbcal's caches give them are touched, and the folders stay (a process running
    beside it writes its next entries there): it loses nothing but speed, each cache is rebuilt
    on its next miss.  A file or folder that cannot be removed or read is listed in
    ``problems`` and the rest are removed."""
    folder = cache_dir() if folder is None else folder
    if folder is None:
        return Cleared(0, 0)
    unknown = [p for p in (parts or ()) if p not in CACHE_PARTS]
    if unknown:
        raise ValueError(f"no cache part named {unknown[0]!r} (parts: {', '.join(CACHE_PARTS)})")
    count = total = 0
    problems: list[str] = []
    for part in parts or CACHE_PARTS:
        try:
            files = _cache_files(folder, part)
        except OSError as err:
            problems.append(f"{folder / part}: {err.strerror or err}")
            continue
        for path, st in files:
            if _remove(path, problems):
                count, total = count + 1, total + st.st_size
    return Cleared(count, total, tuple(problems))


# The parts holding programs, which grow with every new problem structure; the others are small
# (meshes, the grammar) or bounded by their own count (syntax).
PROGRAM_PARTS = ("exports", "jax")
DEFAULT_MAX_MB = 256.0
_TRIM_TO = 0.9  # a trim leaves this fraction of the bound: not one removal per new program


def max_part_bytes() -> int:
    """The size in bytes that each of :data:`PROGRAM_PARTS` is kept under: ``MBCAL_CACHE_MAX_MB``
    megabytes (of 2²⁰ bytes, as ``mbcal cache`` counts them; default :data:`DEFAULT_MAX_MB`).  A
    value that is not a positive number is an error (:class:`~mbcal.errors.MbcalError`), not a
    silent default."""
    text = os.environ.get("MBCAL_CACHE_MAX_MB", "").strip()
    if not text:
        return int(DEFAULT_MAX_MB * 2**20)
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise MbcalError(
            f"MBCAL_CACHE_MAX_MB={text!r}: not a positive number of megabytes (default {DEFAULT_MAX_MB:g})"
        )
    return max(1, int(value * 2**20))


def _entry_of(part: str, name: str) -> str:
    """The entry a file belongs to: JAX keeps an entry as ``<key>-cache`` and, when its own
    eviction is on, ``<key>-atime``; an interrupted write's leftover is an entry of its own."""
    if part == "jax" and (name.endswith("-cache") or name.endswith("-atime")):
        return name.rsplit("-", 1)[0]
    if part == "exports" and name.endswith(".recipe.json"):  # an exported program's inputs: one entry with it
        return name[: -len(".recipe.json")] + ".jaxexport"
    return name


def trim_programs(folder: Path | None = None, limit: int | None = None, keep: Path | None = None) -> Cleared:
    """Remove the least recently used entries of each of :data:`PROGRAM_PARTS` of the cache folder
    (``folder``, default :func:`cache_dir`) that holds more than ``limit`` bytes (default
    :func:`max_part_bytes`), down to 90 % of it.  Last use is a file's modification or access
    time, whichever is later: mbcal marks an exported program when it loads it, and the file
    system marks JAX's entries when they are read (with Linux's default ``relatime``, at least
    once a day).  Only files with the names these caches give them are touched; one that cannot
    be removed is skipped (a concurrent process may have removed it): it loses nothing but speed.
    ``keep``: a file never removed (the entry just written)."""
    folder = cache_dir() if folder is None else folder
    limit = max_part_bytes() if limit is None else limit
    count = total = 0
    problems: list[str] = []
    if folder is None:
        return Cleared(0, 0)
    for part in PROGRAM_PARTS:
        entries: dict[str, list[tuple[Path, int, float]]] = {}
        try:
            files = _cache_files(folder, part)
        except OSError:  # unreadable: nothing to trim there
            continue
        for path, st in files:
            entries.setdefault(_entry_of(part, path.name), []).append((path, st.st_size, max(st.st_mtime, st.st_atime)))
        held = sum(size for items in entries.values() for _, size, _ in items)
        if held <= limit:
            continue
        by_use = sorted(entries.values(), key=lambda items: max(used for _, _, used in items))
        by_use = [items for items in by_use if all(path != keep for path, _, _ in items)]
        for items in by_use:
            if held <= _TRIM_TO * limit:
                break
            # JAX's program before its access-time file: JAX's own eviction, when a user turns it
            # on, reads the access time of every program it finds
            for path, size, _ in sorted(items, key=lambda item: item[0].name.endswith("-atime")):
                if _remove(path, problems):
                    count, total = count + 1, total + size
                held -= size
    return Cleared(count, total, tuple(problems))


@functools.lru_cache(maxsize=1)
def enable_compilation_cache() -> Path | None:
    """Point JAX's persistent compilation cache at ``cache_dir()/jax`` (once per process)."""
    from mbcal._jax import jax  # here, not at import time (see _export_module)

    folder = cache_dir()
    if folder is None:
        return None
    try:
        (folder / "jax").mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # an unwritable home: run without a cache
    jax.config.update("jax_compilation_cache_dir", str(folder / "jax"))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    return folder / "jax"


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """A hash of mbcal's own source: a new mbcal never reuses an old exported program.  (Read at
    the first call; the files' being what runs is checked where programs are loaded and saved:
    :func:`source_edited`.)"""
    h = hashlib.sha256()
    root = package_root()
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    grammar = find_bundled("grammar/mdl.lark")
    if grammar is not None:
        h.update(grammar.read_bytes())
    from mbcal._jax import jax

    h.update(jax.__version__.encode())
    return h.hexdigest()


_SOURCE_LOCK = threading.Lock()
_SOURCE_CHECK: dict[str, Any] = {"modules": -1, "at": -math.inf, "edited": False, "said": False}


def source_edited(*, exact: bool = False) -> bool:
    """Whether one of mbcal's source files was saved, added or removed since ``import mbcal``
    (:mod:`mbcal._sources`): the code that runs is then not the code the cache's keys hash (an
    edit beside a running notebook, an upgrade under a long process, a module imported or
    reloaded after the edit), and the caches of programs and parsed files are neither read nor
    written for the rest of the process.

    Asked before each load, and ``exact`` (looking whatever the time) right before each save:
    otherwise the files are looked at (a stat each, ~1 ms) when modules were imported since the
    last look, else at most once a second (a module imported while a program was traced, or one
    reloaded after an edit, would have slipped through between).  Said once, as a
    :class:`SourceEditedWarning`, in the main thread (a thread of mbcal's own that saw the change
    first leaves it to the main thread's next call)."""
    with _SOURCE_LOCK:
        state = _SOURCE_CHECK
        if not state["edited"]:
            now, modules = time.monotonic(), len(sys.modules)
            if not exact and modules == state["modules"] and now - state["at"] < 1.0:
                return False
            state["modules"], state["at"] = modules, now
            if not _sources.changed():
                return False
            state["edited"] = True
        say = not state["said"] and threading.current_thread() is threading.main_thread()
        state["said"] = state["said"] or say
    if say:
        warnings.warn(
            "mbcal's source files changed since mbcal was imported: this process runs the code as it "
            "was then, so it neither reads nor writes the cache of compiled programs and parsed files "
            "(restart Python to use it)",
            SourceEditedWarning,
            stacklevel=3,
        )
    return True


class SourceEditedWarning(UserWarning):
    """mbcal's source changed under a running process: its caches of programs and parsed files are
    bypassed from then on (:func:`source_edited`)."""


# Digests of the classes' sources, taken once per class: the code that runs is the code that was
# read when its class was made (a file saved since then is not running yet).
_SOURCE_DIGESTS: weakref.WeakKeyDictionary[type, str | None] = weakref.WeakKeyDictionary()


def source_fingerprint(obj: Any) -> str | None:
    """A hash of the source of the package (or single module) that defines ``obj``'s class: a
    plugin's measurement model whose code changed never reuses a program exported with the old
    code.  None when the code has no file to read (defined in an interactive session).  Taken the
    first time a class is asked for (mbcal asks when a plugin is registered or loaded), not again:
    a file edited while the process runs the old code does not stand for it."""
    cls = type(obj)
    try:
        return _SOURCE_DIGESTS[cls]
    except KeyError:
        pass
    except TypeError:  # a class that cannot be weakly referenced: read every time
        return _source_digest(cls)
    digest = _source_digest(cls)
    _SOURCE_DIGESTS[cls] = digest
    return digest


def _source_digest(cls: type) -> str | None:
    name = cls.__module__
    top = sys.modules.get(name.split(".")[0])
    module = sys.modules.get(name)
    roots = [Path(p) for p in getattr(top, "__path__", [])] if name != "__main__" else []
    files = sorted(f for root in roots for f in root.rglob("*.py"))
    if not files:
        single = getattr(module, "__file__", None)
        if not single:
            return None
        files = [Path(single)]
    h = hashlib.sha256()
    for path in files:
        try:
            h.update(path.as_posix().encode() + b"\x1f" + path.read_bytes())
        except OSError:
            return None
    return h.hexdigest()


class Hasher:
    """A small helper to fingerprint mixed content (text, numbers, arrays, files)."""

    def __init__(self):
        self._h = hashlib.sha256()

    def add(self, *items: Any) -> Hasher:
        for item in items:
            if isinstance(item, np.ndarray):
                self._h.update(str((item.dtype, item.shape)).encode())
                self._h.update(np.ascontiguousarray(item).tobytes())
            elif isinstance(item, (bytes, bytearray)):
                self._h.update(item)
            else:
                self._h.update(repr(item).encode())
            self._h.update(b"\x1f")
        return self

    def add_file(self, path: str | os.PathLike[str]) -> Hasher:
        try:
            self._h.update(Path(path).read_bytes())
        except OSError:
            self._h.update(f"<unreadable {path}>".encode())
        return self

    def copy(self) -> Hasher:
        """A hasher that goes on from what this one has taken (this one is unchanged)."""
        other = Hasher()
        other._h = self._h.copy()
        return other

    def hexdigest(self) -> str:
        return self._h.hexdigest()


@functools.lru_cache(maxsize=1)
def _export_module() -> Any:
    """``jax.export``, or None without ``flatbuffers`` (imported on first use, like JAX itself:
    the parser imports this module for :func:`cache_dir` and must not load JAX)."""
    try:  # without them (a broken install) the exported-program cache is off, nothing else
        import flatbuffers  # noqa: F401  - jax.export's serialisation needs it
        from jax import export
    except ImportError:  # pragma: no cover
        return None
    return export


def recipe_path(key: str) -> Path | None:
    """Where the persistent cache keeps the recipe of an exported program's inputs
    (:mod:`mbcal.staging`), None without a cache: beside the program, trimmed with it."""
    folder = cache_dir()
    return None if folder is None or source_edited() else folder / "exports" / f"{key}.recipe.json"


def exported(key: str, jitted: Callable, *example: Any, keep: bool = True) -> Callable:
    """A callable equivalent to ``jitted`` for arguments shaped like ``example``.

    The first process to ask for ``key`` traces ``jitted`` and saves the lowered program; later
    processes load it without tracing.  Without a cache (or without ``flatbuffers``, which
    ``jax.export`` needs to serialise), ``jitted`` itself is returned.  ``keep``: remember the
    loaded program in this process (a small LRU); False when the caller keeps it itself.
    """
    folder = cache_dir()
    if folder is None or source_edited():
        return jitted
    export = _export_module()
    if export is None:
        return jitted
    if not keep:
        return _load_or_export(export, folder, key, jitted, example)
    return _LOADED.get(key, lambda: _load_or_export(export, folder, key, jitted, example))


def _load_or_export(export: Any, folder: Path, key: str, jitted: Callable, example: tuple) -> Callable:
    limit = max_part_bytes()  # a bad MBCAL_CACHE_MAX_MB is said at once, not at the next new program
    enable_compilation_cache()
    path = folder / "exports" / f"{key}.jaxexport"
    program = None
    if path.is_file():
        try:
            program = export.deserialize(bytearray(path.read_bytes()))
        except Exception:  # a truncated or foreign file: export it again
            program = None
        else:
            with contextlib.suppress(OSError):
                os.utime(path)  # its last use, for trim_programs
    if program is None:
        with gc_paused():  # tracing and lowering: see gc_paused
            program = export.export(jitted)(*example)  # type: ignore[arg-type]  # a jax.jit result; stub wants jax.stages.Wrapped
        try:
            if not source_edited(exact=True):  # a module imported while it traced counts too
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(path, bytes(program.serialize()), at_once=True)
                trim_programs(folder, limit, keep=path)
        except OSError:
            pass  # a read-only cache: still correct, only slower next time
    from mbcal._jax import jit

    # Jitted (mbcal's jit: compiled with the collector paused), so that its executable lives (and
    # dies) with this cache's entry: called eagerly, an exported program is compiled into JAX's
    # unbounded cache of primitives instead.
    return jit(program.call)
