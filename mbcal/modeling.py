"""modeler(D, X) → Scene: the virtual environment generator of the seed paper (eq. 13).

A pure function of the parameter vector, written with JAX so that it can be jitted,
differentiated (``jax.jacfwd``) and batched over configurations (``jax.vmap``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mbcal import geometry as geo
from mbcal._jax import jnp
from mbcal.errors import ParameterError
from mbcal.language import ir
from mbcal.language.model import JointInfo, Model
from mbcal.scene import Scene

Array = Any

__all__ = ["modeler", "parameter_vector"]


def parameter_vector(model: Model, values: Mapping[str, float] | None = None) -> np.ndarray:
    """X with the model's nominal values, overridden by ``values`` (SI units, by name)."""
    X = model.nominal.copy()
    for name, value in (values or {}).items():
        X[model.param_index(name)] = float(value)
    return X


def _joint_motion(joint: JointInfo, ev) -> Array:
    q = ev(joint.q)
    if joint.offset is not None:
        q = q + ev(joint.offset)
    axis = ev(joint.axis)
    xp = np if geo.is_constant(q, axis) else jnp
    if joint.kind == "prismatic":
        return geo.translation(xp, axis * q)
    return geo.from_rt(xp, geo.rodrigues(xp, axis, q), xp.zeros(3))


def modeler(model: Model, X: Array | Mapping[str, float]) -> Scene:
    """Build the scene for parameter values ``X``.

    Parameters
    ----------
    model : Model
        The checked description D.
    X : (n_params,) array or mapping
        All parameter values in SI units, in ``model.params`` order; or a mapping from name
        to value, the rest taken at their nominal values.

    Returns
    -------
    Scene
        World poses of frames and shapes, world positions of points, camera intrinsics.
        Differentiable with respect to ``X``.
    """
    if isinstance(X, Mapping):
        X = parameter_vector(model, X)
    if jnp.ndim(X) != 1 or jnp.shape(X)[0] != len(model.params):
        raise ParameterError(
            f"modeler: X must have one value per parameter ({len(model.params)}), got shape {jnp.shape(X)}"
        )
    memo: dict[int, Any] = {}

    def ev(node: ir.Node) -> Array:
        return ir.evaluate(node, X, memo)

    poses: list[Array | None] = []
    for frame in model.frames:
        T = poses[frame.parent] if frame.parent >= 0 else None
        if frame.pose is not None:
            T = geo.compose(T, ev(frame.pose))
        if frame.joint is not None:
            T = geo.compose(T, _joint_motion(frame.joint, ev))
        poses.append(T)

    eye = np.eye(4)

    def pose(i: int) -> Array:
        T = poses[i] if i >= 0 else None
        return eye if T is None else T

    frame_poses = _stack([pose(i) for i in range(len(model.frames))], (0, 4, 4))

    # Points: one matrix product per frame rather than one per point.
    groups: dict[int, list[int]] = {}
    for i, p in enumerate(model.points):
        groups.setdefault(p.frame, []).append(i)
    chunks, order = [], []
    for frame_index, members in groups.items():
        local = _stack([ev(model.points[i].position) for i in members], (0, 3))
        T = poses[frame_index] if frame_index >= 0 else None
        chunks.append(geo.apply(T, local))
        order.extend(members)
    if chunks:
        stacked = chunks[0] if len(chunks) == 1 else jnp.concatenate([jnp.asarray(c) for c in chunks])
        if order != sorted(order):
            stacked = jnp.asarray(stacked)[np.argsort(order)]
        points = jnp.asarray(stacked, dtype=float)
    else:
        points = jnp.zeros((0, 3))

    intrinsics = _stack([_stack([ev(n) for n in c.intrinsics], (5,)) for c in model.cameras], (0, 5))
    distortion = _stack([_stack([ev(n) for n in c.distortion], (5,)) for c in model.cameras], (0, 5))

    shape_poses = []
    shape_dims = []
    for s in model.shapes:
        T = geo.compose(poses[s.frame] if s.frame >= 0 else None, ev(s.pose) if s.pose is not None else None)
        shape_poses.append(eye if T is None else T)
        dims = [ev(n) for n in s.dims] + [0.0] * (3 - len(s.dims))
        shape_dims.append(_stack(dims, (3,)))
    return Scene(
        model=model,
        frame_poses=frame_poses,
        points=points,
        camera_intrinsics=intrinsics,
        camera_distortion=distortion,
        shape_poses=_stack(shape_poses, (0, 4, 4)),
        shape_dims=_stack(shape_dims, (0, 3)),
    )


def _stack(items: list[Array], empty_shape: tuple[int, ...]) -> Array:
    if not items:
        return jnp.zeros(empty_shape)
    if geo.is_constant(*items):
        return jnp.asarray(np.stack([np.asarray(i, dtype=float) for i in items]))
    return jnp.stack([jnp.asarray(i, dtype=float) for i in items])
