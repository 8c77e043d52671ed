"""modeler(D, X) → Scene: the virtual environment generator of the seed paper (eq. 13).

A pure function of the parameter vector, written with JAX so that it can be jitted,
differentiated (``jax.jacfwd``) and batched over configurations (``jax.vmap``).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp, on_host, to_device
from mbcal.errors import ParameterError
from mbcal.language import ir, soa
from mbcal.language import soa_math as sm
from mbcal.language.model import JointInfo, Model
from mbcal.params import ParamView
from mbcal.scene import Scene

Array = Any

__all__ = ["modeler", "parameter_vector", "Needs", "RpyTriple", "rpy_triples"]


def parameter_vector(model: Model, values: Mapping[str, float] | None = None) -> np.ndarray:
    """X with the model's nominal values, overridden by ``values`` (SI units, by name)."""
    X = model.nominal.copy()
    for name, value in (values or {}).items():
        index = model.param_index(name)
        try:  # a number, a NumPy or JAX scalar; not text, a flag, an array or None
            number = None if isinstance(value, (str, bytes, bool)) or np.ndim(value) != 0 else float(value)
        except (TypeError, ValueError):
            number = None
        if number is None or not np.isfinite(number):  # a NaN would pass through the whole scene
            if isinstance(value, jax.core.Tracer):
                raise ParameterError(
                    f"{name}: a traced value (jit, grad, vmap) cannot go through a mapping of values; "
                    "pass X, the whole parameter vector (parameter_vector(model) with your values set in it)"
                )
            raise ParameterError(f"{name}: a value must be a finite number (SI units), got {value!r}")
        X[index] = number
    return X


def _constant_matrix(T: sm.Transform) -> np.ndarray | None:
    """A transform whose entries are all numbers (no traced value) as a (4, 4) matrix, else None."""
    R, t = T
    if not all(isinstance(v, float) for v in (*(v for row in R for v in row), *t)):
        return None
    return np.asarray(sm.transform_to_matrix(T), dtype=float)  # NumPy for numbers: nothing traced


def _joint_motion(joint: JointInfo, ev) -> sm.Transform:
    q = ev(joint.q)
    axis = ev(joint.axis)
    if joint.kind == "prismatic":
        if joint.offset is not None:
            q = sm.add(q, ev(joint.offset))
        return sm.I3, tuple(sm.mul(a, q) for a in axis)
    if joint.offset is not None:
        q = sm.add(q, ev(joint.offset))
    return sm.rodrigues(axis, q), sm.ZERO3


@dataclass(frozen=True)
class Needs:
    """What a computation reads from a scene; everything else the modeler may skip.

    Skipped entries of the scene's arrays hold constants (identity poses, zero points), so a
    consumer must read only what it declared.  ``None`` in a field means all of that kind.
    """

    frames: frozenset[int] | None = frozenset()
    points: frozenset[int] | None = frozenset()
    cameras: frozenset[int] | None = frozenset()
    shapes: frozenset[int] | None = frozenset()

    @staticmethod
    def everything() -> Needs:
        return Needs(None, None, None, None)

    def union(self, other: Needs) -> Needs:
        def join(a, b):
            return None if a is None or b is None else a | b

        return Needs(
            join(self.frames, other.frames),
            join(self.points, other.points),
            join(self.cameras, other.cameras),
            join(self.shapes, other.shapes),
        )


def _selected(wanted: frozenset[int] | None, n: int) -> list[int]:
    return list(range(n)) if wanted is None else sorted(i for i in wanted if 0 <= i < n)


def _frames_needed(model: Model, needs: Needs) -> set[int]:
    """The needed frames and all their ancestors."""
    direct: set[int] = set(_selected(needs.frames, len(model.frames)))
    direct.update(model.points[i].frame for i in _selected(needs.points, len(model.points)))
    direct.update(model.cameras[i].frame for i in _selected(needs.cameras, len(model.cameras)))
    direct.update(model.shapes[i].frame for i in _selected(needs.shapes, len(model.shapes)))
    out: set[int] = set()
    for f in direct:
        while f >= 0 and f not in out:
            out.add(f)
            f = model.frames[f].parent
    return out


@dataclass(frozen=True, eq=False)
class RpyTriple:
    """Three parameters that are only ever used together, as the angles of ``rpy(roll, pitch, yaw)``
    (also inside ``pose(...)``): their orientation can be stepped as a rotation (see
    :func:`rpy_triples`).

    Attributes
    ----------
    params : (int, int, int)
        Positions in X of roll, pitch and yaw.
    nodes : tuple of Op
        The ``rpy`` nodes of the model's graphs that read them.
    """

    params: tuple[int, int, int]
    nodes: tuple[ir.Op, ...]


def _roots(model: Model) -> Iterator[ir.Node]:
    """Every expression graph the modeler evaluates."""
    for f in model.frames:
        if f.pose is not None:
            yield f.pose
        if f.joint is not None:
            yield from (n for n in (f.joint.axis, f.joint.q, f.joint.offset) if n is not None)
    for p in model.points:
        yield p.position
    for c in model.cameras:
        yield from c.intrinsics
        yield from c.distortion
    for sh in model.shapes:
        yield from sh.dims
        if sh.pose is not None:
            yield sh.pose


def _rpy_angles(node: ir.Op | None) -> tuple[int, ...] | None:
    """The parameters of ``rpy(a, b, c)`` when its arguments are three distinct parameters."""
    if node is None or node.op != "rpy":
        return None
    key = tuple(a.index for a in node.args if isinstance(a, ir.ParamRef))
    return key if len(key) == 3 and len(set(key)) == 3 else None


def rpy_triples(model: Model) -> list[RpyTriple]:
    """The roll-pitch-yaw triples of a model: three distinct parameters that appear as the three
    arguments of ``rpy`` (or the angles of ``pose``), each a parameter by itself, and nowhere
    else in the model.

    Such an orientation can be parameterised by a rotation instead of its angles without
    changing anything else: :func:`modeler` then takes the rotation through ``replace``.
    """
    uses: dict[int, list[tuple[ir.Op | None, int]]] = {}
    seen: set[int] = set()
    stack = list(_roots(model))
    for root in stack:
        if isinstance(root, ir.ParamRef):
            uses.setdefault(root.index, []).append((None, -1))  # a parameter used as it is
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, ir.Op):
            for position, arg in enumerate(node.args):
                if isinstance(arg, ir.ParamRef):
                    uses.setdefault(arg.index, []).append((node, position))
                stack.append(arg)
    found: dict[tuple[int, ...], list[ir.Op]] = {}
    for entries in uses.values():
        for user, _ in entries:
            key = _rpy_angles(user)
            if key is not None and user is not None and user not in found.get(key, []):
                found.setdefault(key, []).append(user)
    triples = []
    for key, nodes in found.items():
        # Each angle is used only as that argument of rpy nodes of the same three parameters.
        if all(_rpy_angles(n) == key and pos == k for k, i in enumerate(key) for n, pos in uses[i]):
            triples.append(RpyTriple((key[0], key[1], key[2]), tuple(nodes)))
    return sorted(triples, key=lambda t: t.params)


def modeler(
    model: Model,
    X: Array | Mapping[str, float],
    needs: Needs | None = None,
    *,
    replace: Mapping[ir.Node, Any] | None = None,
) -> Scene:
    """Build the scene for parameter values ``X``.

    Parameters
    ----------
    model : Model
        The checked description D.
    X : (n_params,) array or mapping
        All parameter values in SI units, in ``model.params`` order; or a mapping from name
        to value, the rest taken at their nominal values.
    needs : Needs, optional
        Compute only these frames, points, cameras and shapes (and the frames they hang from);
        the rest of the scene holds constants.  Default: everything.
    replace : mapping, optional
        Values (structure-of-arrays form, :mod:`mbcal.language.soa_math`) that stand in for
        nodes of the model's graphs: the solver's rotation step gives the rotation of an
        ``rpy`` node (see :func:`rpy_triples`) directly, without its angles.

    Returns
    -------
    Scene
        World poses of frames and shapes, world positions of points, camera intrinsics.
        Differentiable with respect to ``X``.
    """
    if isinstance(X, Mapping):
        X = parameter_vector(model, X)
    if not isinstance(X, ParamView) and (jnp.ndim(X) != 1 or jnp.shape(X)[0] != len(model.params)):
        raise ParameterError(
            f"modeler: X must have one value per parameter ({len(model.params)}), got shape {jnp.shape(X)}"
        )
    needs = needs or Needs.everything()
    memo: dict[int, Any] = {id(node): value for node, value in (replace or {}).items()}

    def ev(node: ir.Node):
        return soa.evaluate(node, X, memo)

    # Frame poses as (R, t) of scalars: constants fold away while tracing (see language/soa_math.py).
    # Each pose is kept as (variable part, constant offset): constant offsets are combined with
    # numpy, and a traced product is made only where a parameter enters the chain, so a rigid
    # object under a moving frame costs no operations at all.
    wanted_frames = _frames_needed(model, needs)
    lazy: list[tuple[sm.Transform, np.ndarray] | None] = []
    for index, frame in enumerate(model.frames):
        if index not in wanted_frames:
            lazy.append(None)
            continue
        parent = lazy[frame.parent] if frame.parent >= 0 else (sm.IDENTITY, np.eye(4))
        assert parent is not None  # _frames_needed keeps every ancestor of a wanted frame
        var, const = parent
        for local in (frame.pose, frame.joint):
            if local is None:
                continue
            if isinstance(local, JointInfo):
                value = _joint_motion(local, ev)
            elif isinstance(local, ir.Const):
                const = const @ np.asarray(local.value, dtype=float)
                continue
            else:
                value = ev(local)
            fixed = _constant_matrix(value)
            if fixed is not None:  # a pose or joint of numbers (the model's own values): one constant offset
                const = const @ fixed
                continue
            var = sm.compose(var, sm.compose(sm.from_constant(const, ir.TRANSFORM), value))
            const = np.eye(4)
        lazy.append((var, const))

    eye = np.eye(4)

    def world(frame: int) -> sm.Transform:
        entry = lazy[frame] if frame >= 0 else None
        if entry is None:
            return sm.IDENTITY
        var, const = entry
        return sm.compose(var, sm.from_constant(const, ir.TRANSFORM))

    # Only frames that are read go into the scene's array; ancestors needed to place points and
    # sensors stay out of it (stacking them would materialise their derivatives for nothing).
    read_frames = set(_selected(needs.frames, len(model.frames)))
    read_frames.update(model.cameras[i].frame for i in _selected(needs.cameras, len(model.cameras)))
    if needs.frames is None:
        read_frames.update(r.frame for r in model.ranges)
    frame_poses = _stack(
        [sm.transform_to_matrix(world(i)) if i in read_frames else eye for i in range(len(model.frames))],
        (0, 4, 4),
    )

    # Points: every point is taken through the constant offset of its frame (numpy for a constant
    # point), and the points of all frames that share one variable part — a rigid object's frames,
    # under the parameters that move it — go through it as one array operation: the variable
    # transform is computed once, and the cost does not grow with the number of points or frames.
    point_list = _selected(needs.points, len(model.points))
    groups: dict[int, tuple[sm.Transform, list[np.ndarray], list[Any], list[int], list[int]]] = {}
    for i in point_list:
        p = model.points[i]
        entry = lazy[p.frame] if p.frame >= 0 else None
        var, const = entry if entry is not None else (sm.IDENTITY, np.eye(4))
        group = groups.setdefault(id(var), (var, [], [], [], []))
        if isinstance(p.position, ir.Const):
            group[1].append(const[:3, :3] @ np.asarray(p.position.value, dtype=float) + const[:3, 3])
            group[3].append(i)
        else:
            group[2].append(sm.apply_point(sm.from_constant(const, ir.TRANSFORM), ev(p.position)))
            group[4].append(i)
    blocks: list[Any] = []
    order: list[int] = []
    for var, constant, expressions, constant_index, expression_index in groups.values():
        columns = []
        for k in range(3):
            parts = [np.asarray([c[k] for c in constant], dtype=float)] if constant else []
            if expressions:
                parts.append(sm.stack_scalars([e[k] for e in expressions]))
            columns.append(parts[0] if len(parts) == 1 else jnp.concatenate(parts))
        blocks.append(sm.stack_scalars(sm.apply_point(var, tuple(columns))))
        order.extend(constant_index + expression_index)
    host = on_host(*blocks)
    if not blocks:
        points = to_device(np.zeros((len(model.points), 3)))
    elif host is not None:  # known values (a scene at given numbers): NumPy, then JAX once
        placed = np.zeros((len(model.points), 3))
        placed[np.asarray(order, dtype=np.int64)] = np.concatenate(host)
        points = to_device(placed)
    else:
        stacked = blocks[0] if len(blocks) == 1 else jnp.concatenate([jnp.asarray(b, dtype=float) for b in blocks])
        if len(order) == len(model.points):
            points = stacked if order == sorted(order) else jnp.asarray(stacked)[np.argsort(order)]
        else:
            points = jnp.zeros((len(model.points), 3)).at[np.asarray(order)].set(stacked)
        points = jnp.asarray(points, dtype=float)

    camera_list = set(_selected(needs.cameras, len(model.cameras)))
    zeros5 = np.zeros(5)
    intrinsics = _stack(
        [
            sm.stack_scalars([ev(n) for n in c.intrinsics]) if k in camera_list else zeros5
            for k, c in enumerate(model.cameras)
        ],
        (0, 5),
    )
    distortion = _stack(
        [
            sm.stack_scalars([ev(n) for n in c.distortion]) if k in camera_list else zeros5
            for k, c in enumerate(model.cameras)
        ],
        (0, 5),
    )

    shape_list = set(_selected(needs.shapes, len(model.shapes)))
    shape_poses = []
    shape_dims = []
    for k, s in enumerate(model.shapes):
        if k not in shape_list:
            shape_poses.append(eye)
            shape_dims.append(np.zeros(3))
            continue
        T = world(s.frame)
        if s.pose is not None:
            T = sm.compose(T, ev(s.pose))
        shape_poses.append(sm.transform_to_matrix(T))
        shape_dims.append(sm.stack_scalars([ev(n) for n in s.dims] + [0.0] * (3 - len(s.dims))))
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
        return to_device(np.zeros(empty_shape))
    host = on_host(*items)
    if host is not None:  # known values: stacked in NumPy, handed to JAX once (compiles nothing)
        return to_device(np.stack(host))
    return jnp.stack([jnp.asarray(i, dtype=float) for i in items])
