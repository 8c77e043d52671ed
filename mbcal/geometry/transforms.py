"""Rigid transforms as 4×4 homogeneous matrices, written once for numpy and for JAX.

Every function takes the array module ``xp`` first (``numpy`` or ``jax.numpy``), so the same
code folds constants with numpy when a model is loaded and builds the differentiable graph
with JAX when parameters enter.  Naming follows ``T_a_b``: the pose of frame b in frame a,
mapping b-coordinates to a-coordinates.

Conventions
-----------
* ``rpy(roll, pitch, yaw) = Rz(yaw) · Ry(pitch) · Rx(roll)`` (fixed axes x, y, z; as URDF).
* ``quat(w, x, y, z)``: Hamilton convention, normalised before use.
* Cameras follow OpenCV: x right, y down, z forward along the optical axis.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

Array = Any  # numpy or JAX array

__all__ = [
    "rpy_from_matrix",
    "translation",
    "rot_x",
    "rot_y",
    "rot_z",
    "rpy",
    "axis_angle",
    "quaternion",
    "look_at",
    "from_rt",
    "compose",
    "apply",
    "inverse",
    "is_constant",
]


def is_constant(*values: Any) -> bool:
    """True when every value is a plain number or numpy array (no JAX tracer or array)."""
    return all(isinstance(v, (int, float, np.ndarray, np.generic)) for v in values)


def _module(*values: Any):
    if is_constant(*values):
        return np
    from mbcal._jax import jnp  # lazy: JAX (in float64) only once a traced value shows up; keeps `mbcal check` light

    return jnp


def from_rt(xp, R: Array, t: Array) -> Array:
    """The 4×4 matrix with rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    top = xp.concatenate([xp.asarray(R, dtype=float), xp.reshape(xp.asarray(t, dtype=float), (3, 1))], axis=1)
    return xp.concatenate([top, xp.asarray([[0.0, 0.0, 0.0, 1.0]])], axis=0)


def translation(xp, t: Array) -> Array:
    """A pure translation by ``t`` (3,)."""
    return from_rt(xp, xp.eye(3), t)


def _rotation(xp, R: Array) -> Array:
    return from_rt(xp, R, xp.zeros(3))


def _rx(xp, a):
    c, s = xp.cos(a), xp.sin(a)
    one, zero = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([one, zero, zero]), xp.stack([zero, c, -s]), xp.stack([zero, s, c])])


def _ry(xp, a):
    c, s = xp.cos(a), xp.sin(a)
    one, zero = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([c, zero, s]), xp.stack([zero, one, zero]), xp.stack([-s, zero, c])])


def _rz(xp, a):
    c, s = xp.cos(a), xp.sin(a)
    one, zero = xp.ones_like(c), xp.zeros_like(c)
    return xp.stack([xp.stack([c, -s, zero]), xp.stack([s, c, zero]), xp.stack([zero, zero, one])])


def rot_x(xp, angle: Array) -> Array:
    """Rotation about x by ``angle`` (rad)."""
    return _rotation(xp, _rx(xp, angle))


def rot_y(xp, angle: Array) -> Array:
    """Rotation about y by ``angle`` (rad)."""
    return _rotation(xp, _ry(xp, angle))


def rot_z(xp, angle: Array) -> Array:
    """Rotation about z by ``angle`` (rad)."""
    return _rotation(xp, _rz(xp, angle))


def rpy(xp, roll: Array, pitch: Array, yaw: Array) -> Array:
    """Rz(yaw)·Ry(pitch)·Rx(roll), the URDF convention."""
    return _rotation(xp, _rz(xp, yaw) @ _ry(xp, pitch) @ _rx(xp, roll))


def rpy_from_matrix(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with R = Rz(yaw)·Ry(pitch)·Rx(roll) (URDF's convention; numpy)."""
    pitch = math.atan2(-R[2, 0], math.hypot(R[0, 0], R[1, 0]))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def rodrigues(xp, axis: Array, angle: Array) -> Array:
    """The 3×3 rotation by ``angle`` about the unit vector ``axis``."""
    k = axis
    K = xp.stack(
        [
            xp.stack([xp.zeros_like(k[0]), -k[2], k[1]]),
            xp.stack([k[2], xp.zeros_like(k[0]), -k[0]]),
            xp.stack([-k[1], k[0], xp.zeros_like(k[0])]),
        ]
    )
    return xp.eye(3) + xp.sin(angle) * K + (1.0 - xp.cos(angle)) * (K @ K)


def axis_angle(xp, axis: Array, angle: Array) -> Array:
    """Rotation by ``angle`` about ``axis`` (normalised here; must not be zero)."""
    axis = xp.asarray(axis, dtype=float)
    axis = axis / xp.linalg.norm(axis)
    return _rotation(xp, rodrigues(xp, axis, angle))


def quaternion(xp, w: Array, x: Array, y: Array, z: Array) -> Array:
    """Rotation of the quaternion w + xi + yj + zk (normalised here)."""
    q = xp.stack([w, x, y, z])
    q = q / xp.linalg.norm(q)
    w, x, y, z = q[0], q[1], q[2], q[3]
    R = xp.stack(
        [
            xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)]),
            xp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)]),
            xp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]),
        ]
    )
    return _rotation(xp, R)


def look_at(xp, eye: Array, target: Array, up: Array) -> Array:
    """Pose of a camera at ``eye`` whose optical axis (+z) points at ``target``.

    The image's x axis is horizontal (perpendicular to ``up``) and its y axis points down,
    as in OpenCV.
    """
    eye = xp.asarray(eye, dtype=float)
    z = xp.asarray(target, dtype=float) - eye
    z = z / xp.linalg.norm(z)
    x = xp.cross(z, xp.asarray(up, dtype=float))
    x = x / xp.linalg.norm(x)
    y = xp.cross(z, x)
    return from_rt(xp, xp.stack([x, y, z], axis=1), eye)


def compose(a: Array | None, b: Array | None) -> Array | None:
    """``a @ b`` where None stands for the identity (and stays None when both are)."""
    if a is None:
        return b
    if b is None:
        return a
    return _module(a, b).matmul(a, b)


def apply(T: Array | None, p: Array) -> Array:
    """Transform the point(s) ``p`` (..., 3) by ``T`` (4, 4)."""
    if T is None:
        return p
    return p @ T[:3, :3].T + T[:3, 3]


def inverse(xp, T: Array) -> Array:
    """The inverse of a rigid transform."""
    R, t = T[:3, :3], T[:3, 3]
    return from_rt(xp, R.T, -(R.T @ t))
