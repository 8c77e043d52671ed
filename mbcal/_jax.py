"""Import JAX configured as mbcal needs it: float64 everywhere.

Every mbcal module that uses JAX imports ``jax`` and ``jnp`` from here, so estimation runs in
double precision whatever the order of imports.  mbcal turns on ``jax_enable_x64`` globally
(JAX has no per-call switch); this is documented in docs/api.md.

mbcal's own compiled programs (the solvers, a problem's analysis programs) are built with
:func:`jit`, which passes XLA the options of :func:`compiler_options` for those programs only:
nothing else in the process (a user's own ``jax.jit``) is changed, ``XLA_FLAGS`` is never
written, and an option the user sets there is left to the user.
"""

from __future__ import annotations

import functools
import gc
import importlib.machinery
import importlib.util
import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, ParamSpec, TypeVar

import jax
import jax.numpy as jnp
import numpy as np

from mbcal._collector import end_start_up, gc_paused

jax.config.update("jax_enable_x64", True)

__all__ = [
    "jax",
    "jnp",
    "jit",
    "float64",
    "in_float64",
    "compiler_options",
    "to_device",
    "as_argument",
    "on_host",
    "release_memory",
]

_P = ParamSpec("_P")
_R = TypeVar("_R")


@contextmanager
def float64() -> Iterator[None]:
    """JAX in float64 inside the block, whatever the caller switched after importing mbcal.

    ``import mbcal`` turns ``jax_enable_x64`` on, but a caller may turn it off again (for float32
    code of their own, or another library does).  mbcal's estimation must not then run in float32
    — the solvers silently ~10⁵× less precise — nor stop on a saved program compiled for float64
    ("Dtype mismatch").  Restoring float64 is safe, and better than refusing: ``jax.enable_x64``
    sets the value in force in this thread only, for the block only, so the caller's own JAX
    code keeps the caller's setting after it; JAX keys its traces and compiled programs on the
    setting, so no float32 program is reused here or a float64 one there; and what mbcal's entry
    points return is NumPy.  A thread started inside the block does not inherit the setting:
    its work enters this block itself.  With float64 already on (the usual case) nothing is
    switched.
    """
    if jax.enable_x64.value:  # the value in force in this thread
        yield
        return
    with jax.enable_x64(True):
        yield


def in_float64(function: Callable[_P, _R]) -> Callable[_P, _R]:
    """``function`` run inside :func:`float64`: the guard of mbcal's estimation entry points
    (``least_squares``, ``least_squares_structured``, ``calibrate``, ``observe``, ``simulate``)."""

    @functools.wraps(function)
    def guarded(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with float64():
            return function(*args, **kwargs)

    return guarded


# XLA:CPU options for mbcal's programs (issue 16).  XLA:CPU's newer MLIR "fusion emitters" took
# half of a cold first call (the room's solver: 1.5 s of compile CPU, 0.8 s with XLA's classic
# elemental emitter) and run mbcal's small programs no slower: the seed's solvers 4.3 → 3.9 ms
# and 17.8 → 16.9 ms warm, the 200-view compressed Jacobian 10.7 → 5.7 ms; the structured solver
# (13 and 200 views) ~4 % slower warm for a compile of 3.1 → 1.9 s CPU.  The results agree to
# round-off (XLA fuses differently), not bit for bit.
#
# jaxlib 0.10 hands fused reductions and elementwise work to YNNPACK ("__ynn_fusion"); for the
# small, batched arrays of a model's residual under jacfwd and vmap (the rotation of 24 points as
# a broadcast product summed over one axis of 3, for 6 tangents of 64 restarts) that library call
# cost more than XLA's own loop: the room's 64 restarts 4.2 → 2.8 ms, the arm's 17.4 → 14.5 ms
# (medians of 30, 2 cores), the floor-style loop on a hand-written residual 3.6 → 2.2 ms.  Large
# single matrix products stay with YNNPACK ("individual dot"): without it the dense solver's
# 100-view JᵀJ (10,796 × 609) ran ~15 % slower; the structured solver and the camera calibration
# were unchanged (within 2 %).
#
# XLA's tree-reduction rewriter splits every sum over more than 32 elements (Σr² over 96 or 168
# residuals, the finiteness test of JᵀJ) into a reduce-window and a second reduce, for accuracy on
# GPUs; on the CPU each reduce-window became a kernel of its own that LLVM took ~30 ms of CPU to
# compile (five in the arm's solver).  Without the rewrite XLA:CPU sums with vector accumulators
# in one pass: the arm's compile 0.64 → 0.56 s, the room's 0.54 → 0.51 s, the warm solves and the
# structured solver at 30 and 1,000 views unchanged (A/B, 2 cores); float64 sums of up to a few
# hundred thousand terms lose nothing a fit can see.
_CPU_OPTIONS: dict[str, Any] = {
    "xla_cpu_use_fusion_emitters": False,
    "xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT",
    "xla_disable_hlo_passes": "tree_reduction_rewriter",
}
# The first jaxlib each option is given to (measured there): an XLA that does not know an option
# refuses the compile.  The emitter option is older than mbcal's lowest supported JAX.
_OPTIONS_SINCE: dict[str, tuple[int, ...]] = {
    "xla_cpu_experimental_ynn_fusion_type": (0, 10),
    "xla_cpu_parallel_codegen_split_count": (0, 10),
}

# XLA:CPU hands a program's kernels to LLVM as 32 modules compiled in parallel, and each module
# costs a few milliseconds of CPU however small (the arm's solver: 47 modules, 0.70 s of LLVM's
# CPU).  With one module per usable core the arm's compile was 0.56 → 0.53 s and the room's
# 0.53 → 0.50 s (three A/B pairs each, 2 cores); the structured solver's first call and every warm
# solve unchanged.  Machines with 32 cores or more keep XLA's split.
_XLA_CODEGEN_PARTS = 32


def _codegen_parts() -> int | None:
    """The number of LLVM modules for :func:`compiler_options`: the usable cores, or None (XLA's
    own split) from :data:`_XLA_CODEGEN_PARTS` cores on."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return cores if cores < _XLA_CODEGEN_PARTS else None


def _version(text: str) -> tuple[int, ...]:
    out = []
    for part in text.split(".")[:2]:
        digits = "".join(c for c in part if c.isdigit())
        out.append(int(digits) if digits else 0)
    return tuple(out)


@functools.lru_cache(maxsize=1)
def compiler_options() -> dict[str, Any]:
    """The XLA options :func:`jit` gives mbcal's programs: :data:`_CPU_OPTIONS` and the LLVM
    module split (:func:`_codegen_parts`) on the CPU backend (none on others; YNNPACK's and the
    split from jaxlib 0.10, :data:`_OPTIONS_SINCE`), less any option the
    user sets in ``XLA_FLAGS`` (theirs wins), none at all with ``MBCAL_XLA_OPTIONS=off``.  Part
    of the compiled program's identity, so the persistent compilation cache (:mod:`mbcal.cache`)
    keys on them."""
    if os.environ.get("MBCAL_XLA_OPTIONS", "").lower() in ("0", "off", "no", "false"):
        return {}
    if jax.default_backend() != "cpu":
        return {}
    import jaxlib

    version = _version(jaxlib.__version__)
    flags = os.environ.get("XLA_FLAGS", "")
    options = dict(_CPU_OPTIONS)
    parts = _codegen_parts()
    if parts is not None:
        options["xla_cpu_parallel_codegen_split_count"] = parts
    return {
        name: value for name, value in options.items() if name not in flags and version >= _OPTIONS_SINCE.get(name, ())
    }


def _malloc_trim() -> Callable[[], Any] | None:
    """glibc's ``malloc_trim(0)``, or None where the C library has none (macOS, musl)."""
    try:
        import ctypes

        trim = ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return lambda: trim(0)


_TRIM = _malloc_trim()
_COMPILED = "/jax/core/compile/backend_compile_duration"


RELEASE_BYTES = 16 * 2**20
"""The size of the temporaries (bytes) from which :func:`release_memory` gives the heap back."""


def release_memory(temporaries: int = RELEASE_BYTES, *, collect: bool = False) -> None:
    """Give the heap that freed temporaries left in malloc's arenas back to the system (glibc's
    ``malloc_trim``; nothing elsewhere), when they were at least :data:`RELEASE_BYTES`: large
    NumPy arrays and XLA buffers of a big solve stayed resident after they were freed, and the
    next step's peak came on top of them (issue 15: 2,000 views, ~35 MB of the peak).  Well
    under a millisecond; ``collect``: a garbage collection first, for the cycles that hold
    them (~70 ms with 100,000 measurements alive: after one-off work only, never in a solve)."""
    if temporaries >= RELEASE_BYTES and _TRIM is not None:
        if collect:
            gc.collect()
        _TRIM()


def _after_compile(event: str, duration_secs: float, **_kwargs: str | int) -> None:
    """After any XLA compile of the process: its transient memory (~100 MB after the first solve
    of 2,000 views) back to the system (:func:`release_memory`)."""
    if event == _COMPILED:
        release_memory()


jax.monitoring.register_event_duration_secs_listener(_after_compile)


_LAPACK_MODULES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")
_LAPACK_LOCK = threading.Lock()
_LAPACK_DONE: list[bool] = []  # [whether prepare_lapack gave jaxlib its tables] once it has run


def prepare_lapack() -> bool:
    """Give jaxlib its LAPACK without importing ``scipy.linalg`` (issue 16); True when done so.

    On the CPU, jaxlib finds LAPACK and BLAS through the function tables of SciPy's two Cython
    modules, which it imports by name the first time a program is lowered that solves a linear
    system, and every time an exported program is lowered (``jax.export``: any of mbcal's cached
    programs).  Importing ``scipy.linalg.cython_blas`` runs ``scipy.linalg``'s ``__init__``,
    ~0.11 s of every command on the 2-core machine, though the command uses nothing else of it.
    Here the two extension modules are loaded from their files (~0.02 s with ``import scipy``),
    jaxlib reads its tables from them (once per process), and they leave ``sys.modules`` again,
    so that a later ``import scipy.linalg`` is the ordinary one (it finds the same loaded
    modules).  This runs under Python's import lock, so no other thread can import a module while
    the two stand half-made in ``sys.modules``.  Anything unexpected — ``scipy.linalg`` already
    imported, another backend, another SciPy or jaxlib or Python — and nothing is done: jaxlib
    imports ``scipy.linalg`` itself as before."""
    with _LAPACK_LOCK:
        if not _LAPACK_DONE:
            _LAPACK_DONE.append(_load_lapack_tables())
        return _LAPACK_DONE[0]


def _load_lapack_tables() -> bool:
    if "scipy.linalg" in sys.modules or jax.default_backend() != "cpu":
        return False
    try:
        import _imp

        from jax._src.lax.linalg import initialize_lapack

        package = importlib.util.find_spec("scipy.linalg")  # imports the top-level scipy only
    except Exception:  # pragma: no cover - another layout: jaxlib imports scipy.linalg itself
        return False
    if package is None or not package.submodule_search_locations:
        return False
    added: list[str] = []
    _imp.acquire_lock()  # re-entrant for this thread: the modules' own imports still work
    try:
        for name in _LAPACK_MODULES:
            spec = importlib.machinery.PathFinder.find_spec(name, list(package.submodule_search_locations))
            if spec is None or spec.loader is None or name in sys.modules:
                return False
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            added.append(name)
            spec.loader.exec_module(module)
        initialize_lapack()
    except Exception:  # pragma: no cover - another layout: jaxlib imports scipy.linalg itself
        return False
    finally:
        for name in added:
            sys.modules.pop(name, None)
        _imp.release_lock()
    return True


def jit(fun: Callable, **kwargs: Any) -> Any:
    """``jax.jit(fun, **kwargs)`` with mbcal's XLA options (:func:`compiler_options`): used for
    mbcal's own programs only; traced, lowered and compiled with Python's garbage collector
    paused (:func:`mbcal._collector.gc_paused`).  The first call also readies jaxlib's LAPACK
    (:func:`prepare_lapack`)."""
    prepare_lapack()
    options = compiler_options()
    plain = jax.jit(fun, **kwargs)
    return _Program(jax.jit(fun, compiler_options=options, **kwargs) if options else plain, plain)


def _top_level() -> bool:
    """Whether no JAX transformation is tracing here (JAX accepts compiler options only then)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:  # pragma: no cover - another JAX: options only for calls with concrete values
        return False
    return bool(trace_state_clean())


class _Program:
    """A jitted program of mbcal's that compiles with :func:`compiler_options` when called (or
    traced, lowered) at top level, and is the plain ``jax.jit`` inside another trace — a user's
    ``jit``, ``vmap`` or ``grad`` around it, which JAX refuses for a program with options.  It
    has ``jax.jit``'s ``__call__``, ``trace`` and ``lower`` (``jax.export`` takes it); at top
    level each runs with the garbage collector paused (:func:`mbcal._collector.gc_paused`: a
    warm call costs a microsecond more; not under ``jax.disable_jit``, where nothing compiles);
    any of them ends the command line's start-up pause."""

    __slots__ = ("_options", "_plain")

    def __init__(self, with_options: Any, plain: Any):
        self._options, self._plain = with_options, plain

    def _run(self, method: str, /, *args: Any, **kwargs: Any) -> Any:
        if not _top_level():
            end_start_up()
            return getattr(self._plain, method)(*args, **kwargs)
        run = getattr(self._options, method)
        if getattr(jax.config, "jax_disable_jit", False):  # op by op in Python: no compile, the collector stays
            end_start_up()
            return run(*args, **kwargs)
        with gc_paused():
            return run(*args, **kwargs)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._run("__call__", *args, **kwargs)

    def trace(self, *args: Any, **kwargs: Any) -> Any:
        return self._run("trace", *args, **kwargs)

    def lower(self, *args: Any, **kwargs: Any) -> Any:
        return self._run("lower", *args, **kwargs)

    def eval_shape(self, *args: Any, **kwargs: Any) -> Any:
        return self._plain.eval_shape(*args, **kwargs)


def to_device(value: Any, dtype: Any = None) -> Any:
    """``value`` as a JAX array, without compiling anything.

    ``jnp.asarray`` of a NumPy array runs a small compiled program, one per new shape and dtype
    (about 80 ms the first time in a process, 20 ms from the compilation cache: a command that
    hands a dozen arrays to JAX spent 0.3 s on it); ``jax.device_put`` only copies (issue 16).
    JAX arrays and tracers are returned as they are (converted when ``dtype`` differs).
    """
    if isinstance(value, jax.Array):
        return value if dtype is None or value.dtype == np.dtype(dtype) else value.astype(dtype)
    return jax.device_put(np.asarray(value, dtype=dtype))


def as_argument(value: Any) -> Any:
    """``value`` for a compiled program's call: a JAX array as it is, anything else as a NumPy
    array, which the call takes as it is (~3 µs; :func:`to_device`'s copy costs ~30 µs, a third of
    the Python around a warm solve of the seed's room: 2.44 → 2.31 ms; issue 16)."""
    return value if isinstance(value, jax.Array) else np.asarray(value)


def on_host(*values: Any) -> list[np.ndarray] | None:
    """The values as NumPy arrays when none is being traced (numbers, NumPy or concrete JAX
    arrays), else None.  Assembling a scene from known values in NumPy and handing the result
    to JAX once (:func:`to_device`) compiles nothing; ``jnp.stack``/``reshape`` of them compiled
    one small program per shape (~0.1 s in a fresh process, issue 16)."""
    if any(isinstance(v, jax.core.Tracer) for v in values):
        return None
    return [np.asarray(v, dtype=float) for v in values]
