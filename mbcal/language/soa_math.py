"""Scalars, vectors and transforms in "structure of arrays" form, and their arithmetic.

A scalar is a Python float (a constant known when tracing) or a JAX array; a vector is a tuple
of scalars; a transform is a pair (R, t) of a 3×3 tuple of scalars and a 3-tuple.  Arithmetic
skips exact zeros and ones at trace time, so a rotation about z composed with a translation
produces only the few products that are not trivially zero.  Under ``jit``, ``vmap`` and
``jacfwd`` everything then becomes a handful of large fused elementwise kernels, instead of many
tiny batched matrix products — which XLA runs slowly on a CPU.

These are the kernels: :mod:`mbcal.language.functions` builds the operations of the expression
graph from them and :mod:`mbcal.language.soa` evaluates graphs with them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from mbcal.language.graph import SCALAR, TRANSFORM, VECTOR

Scalar = Any  # float or jax array
Vec = tuple
Transform = tuple  # (R: 3x3 tuple, t: 3-tuple)

__all__ = [
    "Scalar",
    "Vec",
    "Transform",
    "jnp",
    "add",
    "sub",
    "mul",
    "neg",
    "div",
    "total",
    "sin",
    "cos",
    "sqrt",
    "numpy_function",
    "broadcast",
    "minimum",
    "maximum",
    "fold",
    "I3",
    "ZERO3",
    "IDENTITY",
    "matmul3",
    "matvec3",
    "compose",
    "apply_point",
    "rotation",
    "rodrigues",
    "rodrigues_cs",
    "rpy",
    "rotation_vector",
    "rotation_step",
    "axis_angle",
    "quaternion",
    "normalise",
    "cross",
    "look_at",
    "from_constant",
    "to_array",
    "to_arrays",
    "stack_scalars",
    "transform_to_matrix",
]


def jnp() -> Any:
    """``jax.numpy``, configured for float64 by :mod:`mbcal._jax`."""
    # JAX is heavy: imported on the first traced value, so that `mbcal check` does not pay for it.
    from mbcal._jax import jnp as _jnp

    return _jnp


def _is(v: Any, c: float) -> bool:
    return isinstance(v, float) and v == c


def add(a: Scalar, b: Scalar) -> Scalar:
    """``a + b``, skipping a constant zero."""
    if _is(a, 0.0):
        return b
    if _is(b, 0.0):
        return a
    return a + b


def sub(a: Scalar, b: Scalar) -> Scalar:
    """``a - b``, skipping a constant zero."""
    if _is(b, 0.0):
        return a
    if isinstance(a, float) and isinstance(b, float):
        return a - b
    if _is(a, 0.0):
        return -b
    return a - b


def mul(a: Scalar, b: Scalar) -> Scalar:
    """``a * b``, skipping constant zeros, ones and minus ones."""
    if _is(a, 0.0) or _is(b, 0.0):
        return 0.0
    if _is(a, 1.0):
        return b
    if _is(b, 1.0):
        return a
    if _is(a, -1.0):
        return neg(b)
    if _is(b, -1.0):
        return neg(a)
    return a * b


def neg(a: Scalar) -> Scalar:
    """``-a``."""
    return -a


def constant(f: Callable[..., Any], *args: float) -> float:
    """``f`` of constants with IEEE results, as the traced program computes them: a division by
    zero is ±inf, an overflow inf, a fractional power of a negative number NaN — not Python's
    ZeroDivisionError, OverflowError or complex number (a known value of a model is a constant
    while tracing, issue 16)."""
    with np.errstate(all="ignore"):
        return float(f(*(np.float64(a) for a in args)))


def div(a: Scalar, b: Scalar) -> Scalar:
    """``a / b``, skipping a constant one below and a constant zero on top."""
    if _is(b, 1.0):
        return a
    if _is(a, 0.0) and not _is(b, 0.0):
        return 0.0
    if isinstance(a, float) and isinstance(b, float):
        return constant(np.divide, a, b)
    return a / b


def total(items: Iterable[Scalar]) -> Scalar:
    """The sum of scalars, skipping constant zeros."""
    out: Scalar = 0.0
    for v in items:
        out = add(out, v)
    return out


def numpy_function(name: str, a: Scalar) -> Scalar:
    """``numpy.<name>(a)`` on a constant (a float again), ``jax.numpy.<name>(a)`` otherwise."""
    if isinstance(a, float):
        return constant(getattr(np, name), a)
    return getattr(jnp(), name)(a)


def sin(a: Scalar) -> Scalar:
    """``sin(a)``; exactly 0.0 for a constant 0."""
    return 0.0 if _is(a, 0.0) else numpy_function("sin", a)


def cos(a: Scalar) -> Scalar:
    """``cos(a)``; exactly 1.0 for a constant 0."""
    return 1.0 if _is(a, 0.0) else numpy_function("cos", a)


def sqrt(a: Scalar) -> Scalar:
    """``sqrt(a)``."""
    return numpy_function("sqrt", a)


def broadcast(f: Callable[[Scalar, Scalar], Scalar], a: Any, b: Any) -> Any:
    """``f`` applied componentwise to scalars or vectors (a scalar meets every component)."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return tuple(f(x, y) for x, y in zip(a, b))
    if isinstance(a, tuple):
        return tuple(f(x, b) for x in a)
    if isinstance(b, tuple):
        return tuple(f(a, y) for y in b)
    return f(a, b)


def minimum(a: Scalar, b: Scalar) -> Scalar:
    """The smaller of two scalars, by selection (see ``min`` in :mod:`mbcal.language.functions`)."""
    if isinstance(a, float) and isinstance(b, float):
        return a if a <= b else b  # the selection below, NaN included (Python's min keeps a NaN first)
    return jnp().where(a <= b, a, b)


def maximum(a: Scalar, b: Scalar) -> Scalar:
    """The larger of two scalars, by selection."""
    if isinstance(a, float) and isinstance(b, float):
        return a if a >= b else b
    return jnp().where(a >= b, a, b)


def fold(f: Callable[[Any, Any], Any], items: Sequence[Any]) -> Any:
    """``f(f(items[0], items[1]), items[2]) ...``."""
    out = items[0]
    for v in items[1:]:
        out = f(out, v)
    return out


# ---- transforms -----------------------------------------------------------------------------------

I3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
ZERO3 = (0.0, 0.0, 0.0)
IDENTITY: Transform = (I3, ZERO3)


def matmul3(A: tuple, B: tuple) -> tuple:
    """The product of two 3×3 matrices of scalars."""
    return tuple(tuple(total(mul(A[i][k], B[k][j]) for k in range(3)) for j in range(3)) for i in range(3))


def matvec3(A: tuple, v: Vec) -> Vec:
    """A 3×3 matrix of scalars times a 3-vector."""
    return tuple(total(mul(A[i][k], v[k]) for k in range(3)) for i in range(3))


def compose(a: Transform, b: Transform) -> Transform:
    """a · b."""
    Ra, ta = a
    Rb, tb = b
    return matmul3(Ra, Rb), tuple(add(x, y) for x, y in zip(matvec3(Ra, tb), ta))


def apply_point(T: Transform, p: Vec) -> Vec:
    """T applied to the point p."""
    R, t = T
    return tuple(add(x, y) for x, y in zip(matvec3(R, p), t))


def rotation(axis: int, a: Scalar) -> Transform:
    """The rotation by ``a`` about coordinate axis ``axis`` (0: x, 1: y, 2: z)."""
    return _rot_cs(axis, cos(a), sin(a))


def _rot_cs(axis: int, c: Scalar, s: Scalar) -> Transform:
    if axis == 0:
        R = ((1.0, 0.0, 0.0), (0.0, c, neg(s)), (0.0, s, c))
    elif axis == 1:
        R = ((c, 0.0, s), (0.0, 1.0, 0.0), (neg(s), 0.0, c))
    else:
        R = ((c, neg(s), 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))
    return R, ZERO3


def rodrigues(axis: Vec, angle: Scalar) -> tuple:
    """The 3×3 rotation by ``angle`` about the unit ``axis`` (constant or not)."""
    return rodrigues_cs(axis, cos(angle), sin(angle))


def rodrigues_cs(axis: Vec, c: Scalar, s: Scalar) -> tuple:
    """The 3×3 rotation about the unit ``axis`` whose angle has cosine ``c`` and sine ``s``."""
    if all(isinstance(k, float) for k in axis):
        principal = [i for i, k in enumerate(axis) if k != 0.0]
        if len(principal) == 1:
            i = principal[0]
            return _rot_cs(i, c, s if axis[i] > 0 else neg(s))[0]
    kx, ky, kz = axis
    K = ((0.0, neg(kz), ky), (kz, 0.0, neg(kx)), (neg(ky), kx, 0.0))
    K2 = matmul3(K, K)
    c1 = sub(1.0, c)
    return tuple(tuple(add(I3[i][j], add(mul(s, K[i][j]), mul(c1, K2[i][j]))) for j in range(3)) for i in range(3))


def rpy(r: Scalar, p: Scalar, y: Scalar) -> Transform:
    """Roll, pitch, yaw: Rz(y) · Ry(p) · Rx(r), as :func:`mbcal.geometry.transforms.rpy`."""
    return compose(compose(rotation(2, y), rotation(1, p)), rotation(0, r))


def rotation_vector(w: Vec) -> tuple:
    """The 3×3 rotation exp([w]×) of a rotation vector w (axis · angle), smooth at w = 0.

    R = I + A [w]× + B [w]×² with A = sin θ / θ and B = (1 − cos θ) / θ² = 2 sin²(θ/2) / θ²;
    below θ = 1e-6 their Taylor series are used, so forward-mode derivatives at w = 0 are exact
    (∂R/∂w_k = [e_k]×) and never NaN.
    """
    xp = jnp()
    wx, wy, wz = w
    t2 = wx * wx + wy * wy + wz * wz
    small = t2 < 1e-12
    safe = xp.where(small, 1.0, t2)
    theta = xp.sqrt(safe)
    half = xp.sin(0.5 * theta)
    A = xp.where(small, 1.0 - t2 / 6.0, xp.sin(theta) / theta)
    B = xp.where(small, 0.5 - t2 / 24.0, 2.0 * half * half / safe)
    K = ((0.0, neg(wz), wy), (wz, 0.0, neg(wx)), (neg(wy), wx, 0.0))
    K2 = matmul3(K, K)
    return tuple(tuple(add(I3[i][j], add(mul(A, K[i][j]), mul(B, K2[i][j]))) for j in range(3)) for i in range(3))


def rotation_step(w: Vec) -> tuple:
    """I + [w]×: the rotation exp([w]×) to first order in w — exact in value and first derivative
    at w = 0, which is all a Jacobian about the current orientation reads.

    The solver's Jacobian in local coordinates uses this instead of :func:`rotation_vector`: the
    exact map's square root, sines and branches, with their derivatives, were evaluated for every
    point seen in a configuration (XLA fuses them into the per-point kernels), which made the
    Jacobian of a 500-view camera calibration ~2.5× slower (issue 15).
    """
    wx, wy, wz = w
    return ((1.0, neg(wz), wy), (wz, 1.0, neg(wx)), (neg(wy), wx, 1.0))


def axis_angle(axis: Vec, angle: Scalar) -> Transform:
    """The rotation by ``angle`` about ``axis`` (normalised here)."""
    norm = sqrt(total(mul(k, k) for k in axis))
    unit = tuple(div(k, norm) for k in axis)
    return rodrigues(unit, angle), ZERO3


def quaternion(w: Scalar, x: Scalar, y: Scalar, z: Scalar) -> Transform:
    """The rotation of a quaternion (Hamilton, normalised here)."""
    norm = sqrt(total(mul(v, v) for v in (w, x, y, z)))
    w, x, y, z = (div(v, norm) for v in (w, x, y, z))

    def two(a: Scalar, b: Scalar) -> Scalar:
        return mul(2.0, mul(a, b))

    R = (
        (sub(1.0, add(two(y, y), two(z, z))), sub(two(x, y), two(z, w)), add(two(x, z), two(y, w))),
        (add(two(x, y), two(z, w)), sub(1.0, add(two(x, x), two(z, z))), sub(two(y, z), two(x, w))),
        (sub(two(x, z), two(y, w)), add(two(y, z), two(x, w)), sub(1.0, add(two(x, x), two(y, y)))),
    )
    return R, ZERO3


def normalise(v: Vec) -> Vec:
    """``v / |v|``."""
    n = sqrt(total(mul(c, c) for c in v))
    return tuple(div(c, n) for c in v)


def cross(a: Vec, b: Vec) -> Vec:
    """The cross product of two 3-vectors."""
    return (
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    )


def look_at(eye: Vec, target: Vec, up: Vec) -> Transform:
    """The pose at ``eye`` with z towards ``target`` and x perpendicular to ``up`` (OpenCV axes)."""
    z = normalise(tuple(sub(t, e) for t, e in zip(target, eye)))
    x = normalise(cross(z, up))
    y = cross(z, x)
    R = tuple((x[i], y[i], z[i]) for i in range(3))
    return R, tuple(eye)


# ---- conversions ----------------------------------------------------------------------------------


def from_constant(value: np.ndarray, kind: str) -> Any:
    """A numpy constant in SoA form (Python floats)."""
    v = np.asarray(value, dtype=float)
    if kind == SCALAR:
        return float(v)
    if kind == VECTOR:
        return tuple(float(x) for x in v)
    R = tuple(tuple(float(x) for x in row) for row in v[:3, :3])
    return R, tuple(float(x) for x in v[:3, 3])


def to_array(v: Scalar) -> Any:
    """A scalar as a JAX array (constants included)."""
    return jnp().asarray(v, dtype=float)


def to_arrays(value: Any, kind: str) -> Any:
    """An SoA value as an ordinary array: scalar (), vector (n,), transform (4, 4)."""
    if kind == SCALAR:
        return to_array(value)
    if kind == VECTOR:
        return stack_scalars(value)
    R, t = value
    rows = [[R[i][0], R[i][1], R[i][2], t[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    flat = stack_scalars([v for row in rows for v in row])
    from mbcal._jax import on_host

    host = on_host(flat)
    if host is not None:  # known values: NumPy, no compiled reshape (issue 16); JAX gets the scene once
        return np.reshape(host[0], host[0].shape[:-1] + (4, 4))
    return jnp().reshape(flat, (4, 4))


def stack_scalars(values: Sequence[Scalar]) -> Any:
    """Stack scalars (floats, numpy or JAX arrays that broadcast together) along a new last axis."""
    if all(isinstance(v, (float, np.ndarray)) for v in values):
        # NumPy (not jnp.asarray, which compiles a program per shape, nor a device copy per call:
        # the modeler hands its finished arrays to JAX once; issue 16)
        return np.stack(np.broadcast_arrays(*[np.asarray(v, dtype=float) for v in values]), axis=-1)
    xp = jnp()
    shape = xp.broadcast_shapes(*[xp.shape(v) for v in values])
    items = [xp.broadcast_to(xp.asarray(v, dtype=float), shape) for v in values]
    return xp.stack(items, axis=-1)


def transform_to_matrix(T: Transform) -> Any:
    """A transform as a (4, 4) array."""
    return to_arrays(T, TRANSFORM)
