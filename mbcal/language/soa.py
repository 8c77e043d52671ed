"""Expression evaluation in "structure of arrays" form, for the modeler's hot path.

A scalar is a Python float (a constant known when tracing) or a JAX array; a vector is a tuple
of scalars; a transform is a pair (R, t) of a 3×3 tuple of scalars and a 3-tuple.  Arithmetic
skips exact zeros and ones at trace time, so a rotation about z composed with a translation
produces only the few products that are not trivially zero.  Under ``jit``, ``vmap`` and
``jacfwd`` everything then becomes a handful of large fused elementwise kernels, instead of many
tiny batched matrix products — which XLA runs slowly on a CPU.

The semantics are those of :mod:`mbcal.language.ir`; ``tests/test_modeler.py`` checks that both
evaluations agree.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mbcal.language import ir

Scalar = Any  # float or jax array
Vec = tuple
Transform = tuple  # (R: 3x3 tuple, t: 3-tuple)

__all__ = ["evaluate", "to_arrays", "from_constant", "IDENTITY", "compose", "apply_point", "rodrigues"]


def _jnp():
    from mbcal._jax import jnp

    return jnp


def _is(v: Any, c: float) -> bool:
    return isinstance(v, float) and v == c


def add(a: Scalar, b: Scalar) -> Scalar:
    if _is(a, 0.0):
        return b
    if _is(b, 0.0):
        return a
    if isinstance(a, float) and isinstance(b, float):
        return a + b
    return a + b


def sub(a: Scalar, b: Scalar) -> Scalar:
    if _is(b, 0.0):
        return a
    if isinstance(a, float) and isinstance(b, float):
        return a - b
    if _is(a, 0.0):
        return -b
    return a - b


def mul(a: Scalar, b: Scalar) -> Scalar:
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
    return -a


def div(a: Scalar, b: Scalar) -> Scalar:
    if _is(b, 1.0):
        return a
    if _is(a, 0.0):
        return 0.0
    return a / b


def total(items) -> Scalar:
    out: Scalar = 0.0
    for v in items:
        out = add(out, v)
    return out


def _f(name: str, a: Scalar) -> Scalar:
    if isinstance(a, float):
        return float(getattr(np, name)(a))
    return getattr(_jnp(), name)(a)


def sin(a):
    return 0.0 if _is(a, 0.0) else _f("sin", a)


def cos(a):
    return 1.0 if _is(a, 0.0) else _f("cos", a)


def sqrt(a):
    return _f("sqrt", a)


# ---- transforms -----------------------------------------------------------------------------------

I3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
ZERO3 = (0.0, 0.0, 0.0)
IDENTITY: Transform = (I3, ZERO3)


def matmul3(A, B):
    return tuple(tuple(total(mul(A[i][k], B[k][j]) for k in range(3)) for j in range(3)) for i in range(3))


def matvec3(A, v):
    return tuple(total(mul(A[i][k], v[k]) for k in range(3)) for i in range(3))


def compose(a: Transform, b: Transform) -> Transform:
    """a · b."""
    Ra, ta = a
    Rb, tb = b
    return matmul3(Ra, Rb), tuple(add(x, y) for x, y in zip(matvec3(Ra, tb), ta))


def apply_point(T: Transform, p: Vec) -> Vec:
    R, t = T
    return tuple(add(x, y) for x, y in zip(matvec3(R, p), t))


def _rot(axis: int, a: Scalar) -> Transform:
    return _rot_cs(axis, cos(a), sin(a))


def _rot_cs(axis: int, c: Scalar, s: Scalar) -> Transform:
    if axis == 0:
        R = ((1.0, 0.0, 0.0), (0.0, c, neg(s)), (0.0, s, c))
    elif axis == 1:
        R = ((c, 0.0, s), (0.0, 1.0, 0.0), (neg(s), 0.0, c))
    else:
        R = ((c, neg(s), 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))
    return R, ZERO3


def rodrigues(axis: Vec, angle: Scalar):
    """The 3×3 rotation by ``angle`` about the unit ``axis`` (constant or not)."""
    return rodrigues_cs(axis, cos(angle), sin(angle))


def rodrigues_cs(axis: Vec, c: Scalar, s: Scalar):
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


def from_constant(value: np.ndarray, kind: str):
    """A numpy constant in SoA form (Python floats)."""
    v = np.asarray(value, dtype=float)
    if kind == ir.SCALAR:
        return float(v)
    if kind == ir.VECTOR:
        return tuple(float(x) for x in v)
    R = tuple(tuple(float(x) for x in row) for row in v[:3, :3])
    return R, tuple(float(x) for x in v[:3, 3])


def _vec_op(f, a, b):
    if isinstance(a, tuple) and isinstance(b, tuple):
        return tuple(f(x, y) for x, y in zip(a, b))
    if isinstance(a, tuple):
        return tuple(f(x, b) for x in a)
    if isinstance(b, tuple):
        return tuple(f(a, y) for y in b)
    return f(a, b)


def _rpy(r, p, y):
    return compose(compose(_rot(2, y), _rot(1, p)), _rot(0, r))


def _axis_angle(axis, angle):
    norm = sqrt(total(mul(k, k) for k in axis))
    unit = tuple(div(k, norm) for k in axis)
    return rodrigues(unit, angle), ZERO3


def _quat(w, x, y, z):
    norm = sqrt(total(mul(v, v) for v in (w, x, y, z)))
    w, x, y, z = (div(v, norm) for v in (w, x, y, z))

    def two(a, b):
        return mul(2.0, mul(a, b))

    R = (
        (sub(1.0, add(two(y, y), two(z, z))), sub(two(x, y), two(z, w)), add(two(x, z), two(y, w))),
        (add(two(x, y), two(z, w)), sub(1.0, add(two(x, x), two(z, z))), sub(two(y, z), two(x, w))),
        (sub(two(x, z), two(y, w)), add(two(y, z), two(x, w)), sub(1.0, add(two(x, x), two(y, y)))),
    )
    return R, ZERO3


def _normalise(v):
    n = sqrt(total(mul(c, c) for c in v))
    return tuple(div(c, n) for c in v)


def _cross(a, b):
    return (
        sub(mul(a[1], b[2]), mul(a[2], b[1])),
        sub(mul(a[2], b[0]), mul(a[0], b[2])),
        sub(mul(a[0], b[1]), mul(a[1], b[0])),
    )


def _look_at(eye, target, up):
    z = _normalise(tuple(sub(t, e) for t, e in zip(target, eye)))
    x = _normalise(_cross(z, up))
    y = _cross(z, x)
    R = tuple((x[i], y[i], z[i]) for i in range(3))
    return R, tuple(eye)


def _scalar_fn(name):
    return lambda a: _f(name, a)


def _minimum(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return min(a, b)
    return _jnp().where(a <= b, a, b)


def _maximum(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return max(a, b)
    return _jnp().where(a >= b, a, b)


def _fold(f, items):
    out = items[0]
    for v in items[1:]:
        out = f(out, v)
    return out


OPS = {
    "neg": lambda a: tuple(neg(x) for x in a) if isinstance(a, tuple) else neg(a),
    "add": lambda a, b: _vec_op(add, a, b),
    "sub": lambda a, b: _vec_op(sub, a, b),
    "mul": lambda a, b: _vec_op(mul, a, b),
    "div": lambda a, b: _vec_op(div, a, b),
    "pow": lambda a, b: (a**b) if not (isinstance(a, float) and isinstance(b, float)) else float(a**b),
    "sin": sin,
    "cos": cos,
    "tan": _scalar_fn("tan"),
    "asin": _scalar_fn("arcsin"),
    "acos": _scalar_fn("arccos"),
    "atan": _scalar_fn("arctan"),
    "atan2": lambda a, b: (
        float(np.arctan2(a, b)) if isinstance(a, float) and isinstance(b, float) else _jnp().arctan2(a, b)
    ),
    "sqrt": sqrt,
    "abs": _scalar_fn("abs"),
    "exp": _scalar_fn("exp"),
    "log": _scalar_fn("log"),
    "min": lambda *a: _fold(_minimum, a),
    "max": lambda *a: _fold(_maximum, a),
    "hypot": lambda a, b: sqrt(add(mul(a, a), mul(b, b))),
    "norm": lambda v: sqrt(total(mul(c, c) for c in v)),
    "dot": lambda a, b: total(mul(x, y) for x, y in zip(a, b)),
    "cross": _cross,
    "vec": lambda *items: tuple(items),
    "translate": lambda v: (I3, tuple(v)),
    "rot_x": lambda a: _rot(0, a),
    "rot_y": lambda a: _rot(1, a),
    "rot_z": lambda a: _rot(2, a),
    "rpy": _rpy,
    "axis_angle": _axis_angle,
    "quat": _quat,
    "look_at": _look_at,
    "compose": compose,
}


def evaluate(node: ir.Node, X: Any, memo: dict[int, Any]) -> Any:
    """The SoA value of ``node`` (see the module doc); iterative, like :func:`ir.evaluate`."""
    return ir.walk(
        node, memo, lambda n: from_constant(n.value, n.kind), lambda n: X[n.index], lambda name, *a: OPS[name](*a)
    )


def to_array(v: Scalar):
    """A scalar as a JAX array (constants included)."""
    jnp = _jnp()
    return jnp.asarray(v, dtype=float)


def to_arrays(value: Any, kind: str):
    """An SoA value as an ordinary array: scalar (), vector (n,), transform (4, 4)."""
    jnp = _jnp()
    if kind == ir.SCALAR:
        return to_array(value)
    if kind == ir.VECTOR:
        return stack_scalars(value)
    R, t = value
    rows = [[R[i][0], R[i][1], R[i][2], t[i]] for i in range(3)] + [[0.0, 0.0, 0.0, 1.0]]
    return jnp.reshape(stack_scalars([v for row in rows for v in row]), (4, 4))


def stack_scalars(values) -> Any:
    """Stack scalars (floats, numpy or JAX arrays that broadcast together) along a new last axis."""
    jnp = _jnp()
    if all(isinstance(v, (float, np.ndarray)) for v in values):
        return jnp.asarray(np.stack(np.broadcast_arrays(*[np.asarray(v, dtype=float) for v in values]), axis=-1))
    shape = jnp.broadcast_shapes(*[jnp.shape(v) for v in values])
    items = [jnp.broadcast_to(jnp.asarray(v, dtype=float), shape) for v in values]
    return jnp.stack(items, axis=-1)


def transform_to_matrix(T: Transform) -> Any:
    """A transform as a (4, 4) array."""
    return to_arrays(T, ir.TRANSFORM)
