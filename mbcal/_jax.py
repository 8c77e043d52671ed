"""Import JAX configured as mbcal needs it: float64 everywhere.

Every mbcal module that uses JAX imports ``jax`` and ``jnp`` from here, so estimation runs in
double precision whatever the order of imports.  mbcal turns on ``jax_enable_x64`` globally
(JAX has no per-call switch); this is documented in docs/api.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

__all__ = ["jax", "jnp"]
