"""Writing files without losing anything.

Every file mbcal writes goes through :func:`atomic_write`: the data goes to a temporary file
in the target's folder, is flushed to disk, and then renamed over the target in one step, so a
crash or Ctrl-C leaves either the old file or the complete new one — never a partial file.
The file gets the permissions an ordinary write would give it: a new file those of the user's
umask (0644 under umask 022, 0600 under 077), a replaced file its old ones — not the 0600 of
the temporary file.  Inputs are protected: :func:`check_output` refuses to write over a file the
command reads.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import stat
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from mbcal.errors import OutputError

__all__ = [
    "all_or_nothing",
    "atomic_write",
    "atomic_writer",
    "check_output",
    "current_umask",
    "finite_or_null",
    "make_output_folder",
    "OutputError",
]


def finite_or_null(data: Any) -> Any:
    """``data`` with every non-finite number (an unobservable σ, a χ² without degrees of freedom)
    replaced by None, in nested dicts, lists and tuples: JSON has no inf or NaN."""
    if isinstance(data, dict):
        return {k: finite_or_null(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_or_null(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def current_umask() -> int:
    """The process's umask: read from /proc where the system has it (nothing changes), else set and
    restored at once."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_for(target: Path) -> int:
    """Permission bits of a file written to ``target``: kept when it replaces a file, else 0666
    less the umask (what ``open(target, "w")`` gives)."""
    try:
        existing = os.stat(target)
    except OSError:
        return 0o666 & ~current_umask()
    if stat.S_ISREG(existing.st_mode):
        return stat.S_IMODE(existing.st_mode)
    return 0o666 & ~current_umask()


def check_output(
    path: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]] = (), *, overwrite: bool = True
) -> Path:
    """Validate an output path before any work is done.

    Raises
    ------
    OutputError
        The path is one of ``inputs`` (mbcal never overwrites its input), its folder does not
        exist or is not writable, it is a folder or a read-only file, or it exists and
        ``overwrite`` is False.
    """
    out = Path(path)
    resolved = out.resolve()
    for item in inputs:
        if Path(item).resolve() == resolved:
            raise OutputError(f"refusing to overwrite the input file {item}", hint="choose another output name")
    if out.is_dir():
        raise OutputError(f"{out} is a folder; give a file name")
    if not resolved.parent.is_dir():
        raise OutputError(f"cannot write {out}: folder {out.parent} does not exist")
    if not os.access(resolved.parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write {out}: folder {out.parent} is not writable")
    if out.exists() and not os.access(resolved, os.W_OK):
        raise OutputError(f"cannot write {out}: the file is read-only")
    if out.exists() and not overwrite:
        raise OutputError(f"{out} exists; pass --force to replace it")
    return out


INTERRUPTED = threading.Event()
"""Set by the command line's Ctrl-C handler (:func:`mbcal.cli.main`).  Python only prints an
interrupt that lands in a finalizer or a callback and goes on; the flag still stops every later
write (:func:`check_interrupted`), so an interrupted command never leaves an output behind."""


def check_output_folder(path: str | os.PathLike[str], what: str) -> Path:
    """Validate an output folder (made when missing) before any work is done: ``what`` names the
    option in the message (``--overlay``)."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{what} needs a folder; {folder} is a file")
    parent = next((p for p in (folder.resolve(), *folder.resolve().parents) if p.exists()), None)
    if parent is None or not parent.is_dir():
        raise OutputError(f"{what}: cannot make the folder {folder}: {parent} is a file")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{what}: cannot write into {folder}: {parent} is not writable")
    try:  # the system's answer, not only the permission bits (/proc says writable to root)
        os.rmdir(tempfile.mkdtemp(prefix=".mbcal-probe.", dir=parent))
    except OSError as err:
        raise OutputError(f"{what}: cannot write into {folder}: {err.strerror or err}") from None
    return folder


def check_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` when the command line was interrupted (see :data:`INTERRUPTED`)."""
    if INTERRUPTED.is_set():
        raise KeyboardInterrupt


_PROTECTED: contextvars.ContextVar[frozenset[Path]] = contextvars.ContextVar("mbcal_protected", default=frozenset())


@contextlib.contextmanager
def protected_inputs() -> Iterator[None]:
    """Within the block, :func:`protect` adds files that no atomic write may replace: a command's
    inputs, whatever writes — an overlay whose name a photo happens to have too (one folder both
    read and written) is refused, not written over the photo."""
    token = _PROTECTED.set(frozenset())
    try:
        yield
    finally:
        _PROTECTED.reset(token)


def protect(paths: Iterable[str | os.PathLike[str]]) -> None:
    """Add input files to those the current :func:`protected_inputs` block keeps (no-op outside one)."""
    _PROTECTED.set(_PROTECTED.get() | {Path(p).resolve() for p in paths})


def refuse_inputs(paths: Iterable[str | os.PathLike[str]]) -> None:
    """Raise if one of ``paths`` is a file the current :func:`protected_inputs` block keeps: called
    by every atomic write, and before the work by a command that knows its file names early."""
    kept = _PROTECTED.get()
    for path in paths:
        if Path(path).resolve() in kept:
            raise OutputError(
                f"refusing to overwrite the input file {path}", hint="choose another output name or folder"
            )


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str], mode: str = "wb", *, at_once: bool = False) -> Iterator:
    """Open a temporary file that replaces ``path`` only when the block finishes without error.

    The temporary file lies in the target's folder (so the rename is atomic), is flushed to disk,
    gets the target's permissions (see the module doc) and is renamed over the target — inside an
    :func:`all_or_nothing` block when the block ends, unless ``at_once`` (the cache's files: not a
    command's outputs, and another process may trim or clear the folder meanwhile).
    """
    target = Path(path)
    refuse_inputs([target])
    # Beside the name given, not beside what a link there points to: the rename below replaces
    # that name (a link included), and a rename across file systems fails.
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
    except OSError as err:  # said of the file asked for, not of the temporary one beside it
        raise OutputError(f"cannot write {target}: {err.strerror or err}") from None
    try:
        encoding, newline = (None, None) if "b" in mode else ("utf-8", "")
        with os.fdopen(fd, mode, encoding=encoding, newline=newline) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, _mode_for(target))
        check_interrupted()  # an interrupt Python swallowed still stops the write
        pending = None if at_once else _PENDING.get()
        if pending is not None:  # renamed with the command's other outputs (all_or_nothing)
            pending.append((tmp, target))
        else:
            os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# The finished temporary files of an all_or_nothing block and their targets, in the order written.
_PENDING: contextvars.ContextVar[list[tuple[str, Path]] | None] = contextvars.ContextVar(
    "mbcal_pending_outputs", default=None
)
# The folders make_output_folder made in the block (deepest first): removed again, when empty, if
# the block fails (an interrupted solve left its --overlay folder behind, empty).
_MADE: contextvars.ContextVar[list[Path] | None] = contextvars.ContextVar("mbcal_made_folders", default=None)


def make_output_folder(path: str | os.PathLike[str]) -> Path:
    """Make the folder ``path`` (and missing parents) for a command's outputs: within an
    :func:`all_or_nothing` block, the folders made are removed again, when empty, if it fails."""
    folder = Path(path)
    resolved = folder.resolve()  # ('x/../kept/out': 'kept' exists, whatever 'x/..' says)
    missing = [p for p in (resolved, *resolved.parents) if not p.exists()]
    resolved.mkdir(parents=True, exist_ok=True)  # (not 'x' of 'x/..': made, it was never removed)
    made = _MADE.get()
    if made is not None:
        made.extend(missing)
    return folder


@contextlib.contextmanager
def all_or_nothing() -> Iterator[None]:
    """Within the block, each atomic write keeps its finished temporary file, and all are renamed
    over their targets when the block ends without an exception (Ctrl-C held off meanwhile, where
    it can be): a command interrupted half-way — while its overlays are drawn, after its report —
    leaves none of its outputs, not some.  Not for work whose files must appear as it goes (the
    model manager, the studio as a whole: each of its Saves is one block), nor for a block that
    reads back what it wrote.

    A block inside another one is a part that may fail alone (the studio's overlays: a Save
    without them still writes the rest): when it fails, its own files and folders are dropped;
    when it succeeds, they join the enclosing block's, renamed (or dropped) with them."""
    outer_pending, outer_made = _PENDING.get(), _MADE.get()
    pending: list[tuple[str, Path]] = []
    made: list[Path] = []
    token, made_token = _PENDING.set(pending), _MADE.set(made)
    try:
        yield
    except BaseException:
        for tmp, _ in pending:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        for folder in made:  # deepest first; one that holds anything else stays
            with contextlib.suppress(OSError):
                os.rmdir(folder)
        raise
    finally:
        _PENDING.reset(token)
        _MADE.reset(made_token)
    if outer_pending is not None and outer_made is not None:
        outer_pending.extend(pending)
        outer_made[:0] = made  # made inside the enclosing block's folders: removed before them
        return
    with _interrupts_held():
        for k, (tmp, target) in enumerate(pending):
            try:
                os.replace(tmp, target)
            except BaseException:
                for rest, _ in pending[k:]:
                    with contextlib.suppress(OSError):
                        os.unlink(rest)
                raise


@contextlib.contextmanager
def _interrupts_held() -> Iterator[None]:
    """SIGINT blocked for the block (delivered after it), where the platform and thread allow."""
    import signal

    block = getattr(signal, "pthread_sigmask", None)
    if block is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = block(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        block(signal.SIG_SETMASK, previous)


def atomic_write(path: str | os.PathLike[str], data: bytes | str, *, at_once: bool = False) -> None:
    """Write ``data`` to ``path`` atomically (text is written as UTF-8); ``at_once``: see
    :func:`atomic_writer`."""
    with atomic_writer(path, "wb", at_once=at_once) as handle:
        handle.write(data.encode("utf-8") if isinstance(data, str) else data)
