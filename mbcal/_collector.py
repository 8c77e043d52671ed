"""Python's cyclic garbage collector around mbcal's compiles and the command line's start-up.

Tracing a model through ``vmap``, ``jacfwd`` and the Marquardt loop allocates tens of thousands
of small objects, and every few hundred allocations Python's collector runs — now and then over
every object the process holds, ~200,000 once JAX is imported.  Measured on the 2-core machine
(issue 16): ~0.1 s of the seed's room's 0.57 s trace and lowering in a fresh process, and ~0.1 s
of a warm ``mbcal calibrate-camera`` (imports, reading the corners, loading the programs).

* :func:`gc_paused` holds the collector while one of mbcal's programs is traced, lowered and
  compiled (:func:`mbcal._jax.jit`, the exported programs of :mod:`mbcal.cache`); the cycles that
  tracing leaves are collected at the next collection after it.
* :func:`pause_start_up` is for the command line only (a process of mbcal's own, never a
  library caller's): no collections from the start until the first of mbcal's programs is
  called, when everything alive by then — the imported modules, the model, the measurements —
  is moved to Python's permanent generation (``gc.freeze``), which later collections do not
  traverse, and collecting resumes.  A command that runs no program (``check``, ``--help``)
  ends before it matters; the studio's server ends the pause before it serves
  (:func:`end_start_up`).

No JAX here: the command line imports this module before it knows whether it needs JAX.
"""

from __future__ import annotations

import contextlib
import gc
import os
import threading
from collections.abc import Iterator

__all__ = ["gc_paused", "pause_start_up", "end_start_up"]

_LOCK = threading.Lock()
# holders of gc_paused; whether the collector was enabled when the first came; whether the
# command line's start-up pause is on
_state = {"held": 0, "enabled": False, "start_up": False}


def pause_start_up() -> None:
    """No garbage collections until the first of mbcal's programs is called (the command line's
    start-up; see the module's notes).  Nothing when the collector is already off."""
    with _LOCK:
        if gc.isenabled():
            gc.disable()
            _state["start_up"] = True


def _end_start_up_locked() -> bool:
    if not _state["start_up"]:
        return False
    _state["start_up"] = False
    gc.freeze()  # what start-up built stays for the process's life: later collections skip it
    return True


def end_start_up() -> None:
    """End :func:`pause_start_up`'s pause now (a long-running command before it waits)."""
    with _LOCK:
        if _end_start_up_locked():
            _state["enabled"] = True  # for the last holder, if any: the start-up pause is over
            if _state["held"] == 0:
                gc.enable()


def _after_fork_in_child() -> None:
    """A child forked while a thread of the parent held the pause has no such thread: the pause
    ends in it (the collector as it was before), with a new lock."""
    global _LOCK
    _LOCK = threading.Lock()
    if _state["held"]:
        _state["held"] = 0
        if _state["enabled"]:
            gc.enable()


if hasattr(os, "register_at_fork"):  # not on Windows
    os.register_at_fork(after_in_child=_after_fork_in_child)


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Hold Python's garbage collector for the block.  Nested and concurrent holders share one
    pause; the collector is enabled again when the last one leaves, and only if it was enabled
    before the first came (a caller's ``gc.disable()`` stays).  The first holder ends the command
    line's start-up pause (:func:`pause_start_up`), before tracing makes its garbage."""
    with _LOCK:
        if _state["held"] == 0:
            _state["enabled"] = _end_start_up_locked() or gc.isenabled()
            gc.disable()
        _state["held"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _state["held"] -= 1
            if _state["held"] == 0 and _state["enabled"]:
                gc.enable()
