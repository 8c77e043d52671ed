"""Import JAX configured as mbcal needs it: float64 everywhere.

Every mbcal module that uses JAX imports ``jax`` and ``jnp`` from here, so estimation runs in
double precision whatever the order of imports.  mbcal turns on ``jax_enable_x64`` globally
(JAX has no per-call switch); this is documented in docs/api.md.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

__all__ = ["jax", "jnp", "to_device", "on_host"]


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


def on_host(*values: Any) -> list[np.ndarray] | None:
    """The values as NumPy arrays when none is being traced (numbers, NumPy or concrete JAX
    arrays), else None.  Assembling a scene from known values in NumPy and handing the result
    to JAX once (:func:`to_device`) compiles nothing; ``jnp.stack``/``reshape`` of them compiled
    one small program per shape (~0.1 s in a fresh process, issue 16)."""
    if any(isinstance(v, jax.core.Tracer) for v in values):
        return None
    return [np.asarray(v, dtype=float) for v in values]
