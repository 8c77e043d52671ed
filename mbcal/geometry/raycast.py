"""Differentiable ray casting and point-to-surface distances for the scene's shapes.

Two measurement models rest on these kernels: a range sensor (the distance along a ray to the
first surface of the scene) and point-to-surface distance.  Everything is written in JAX
(float64), works under ``jit`` and ``vmap``, and has finite derivatives everywhere: every
square root, norm and division that can meet zero is guarded with the "double where" pattern
(the unsafe input is replaced before the operation, the result is selected after it), so rays
that miss, rays parallel to a face and points on an axis give derivative 0 rather than NaN.
Where a ray hits a smooth part of a surface, the derivative is that of the hit distance.

Every primitive is centred on its own frame's origin with its axis along z (see
:mod:`mbcal.geometry.shapes`); ``dims`` is a length-3 array, zero-padded:

==========  ===========================  ================================================
kind        dims                         surface
==========  ===========================  ================================================
box         (sx, sy, sz)                 full side lengths
cylinder    (radius, length, 0)          solid closed cylinder, z in [-length/2, length/2]
cone        (radius, length, 0)          base disc at z = -length/2, apex at +length/2
sphere      (radius, 0, 0)               the sphere
tube        (outer, inner, length)       outer and inner walls, two annular end faces
rectangle   (sx, sy, 0)                  |x| <= sx/2, |y| <= sy/2 in the plane z = 0
plane       (ignored)                    the infinite plane z = 0
mesh        (scale_x, scale_y, scale_z)  the mesh's triangles, vertices scaled per axis
==========  ===========================  ================================================

Rays are ``origin + t * direction`` for ``t >= t_min``; the returned ``t`` is the ray
parameter, which is the distance when ``direction`` is a unit vector — callers that want
distances (range sensors) must pass unit directions.  Surfaces are two-sided: a ray that
starts inside a solid hits its boundary from within.

Meshes are searched in two passes: every triangle, without derivatives, to find the one hit
first (or the nearest one), then that triangle alone, differentiably — so ``jacfwd`` costs one
triangle per ray and tangent rather than the whole mesh.

Limitations
-----------
* Hits closer than ``t_min`` (default 1e-9) are ignored, so a ray that starts on a surface
  does not see it: leaving a solid it sees nothing (or the next shape), entering one it sees
  the far side; a ray starting on a rectangle, plane or mesh passes through it.
* Where the hit moves from one face to another (box edges, rims, mesh edges, the silhouette
  of a round shape) the distance has a kink or a jump; the derivative there is that of one
  side (or their average).  A grazing ray (tangent to a sphere or cylinder) counts as a hit,
  with the square root's infinite derivative replaced by 0.
* Directions whose component along a face normal (or across an axis) is below 1e-12 of their
  length count as parallel to it.
* Poses must be rigid: world coordinates are mapped with R^T (p - t), not a general inverse.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from mbcal._jax import jnp
from mbcal.geometry.kernels import INF, as_float, min_last
from mbcal.geometry.shapes import get_shape, shape_kinds

Array = Any

__all__ = [
    "RAY_KINDS",
    "ray_hit",
    "surface_distance",
    "cast_rays",
    "distance_to_shapes",
    "scene_cast_rays",
    "scene_distance",
]

# The built-in kinds (every registered kind can be cast against; see shapes.shape_kinds()).
RAY_KINDS: tuple[str, ...] = tuple(shape_kinds())


def ray_hit(kind: str, origin: Array, direction: Array, dims: Array, mesh=None, t_min: float = 1e-9) -> Array:
    """First intersection of rays with one shape, in the shape's own frame.

    Parameters
    ----------
    kind : str
        The shape kind (a registered kind, :func:`mbcal.geometry.shapes.shape_kinds`); static.
    origin : (..., 3) float
        Ray origins in the shape frame.
    direction : (..., 3) float
        Ray directions in the shape frame.  They should be unit vectors: the result is the ray
        parameter ``t``, which is a distance only for unit directions.  A zero direction never
        hits.
    dims : (3,) or (..., 3) float
        The shape's dimensions (see the module docstring); leading axes broadcast with those
        of ``origin``.
    mesh : MeshData, optional
        The triangles of a ``mesh`` shape (numpy constants, static); ignored for other kinds.
    t_min : float
        Hits closer than this are ignored, so a ray that starts on a surface does not hit it.

    Returns
    -------
    t : (...,) float
        Smallest ``t >= t_min`` with ``origin + t * direction`` on the shape's surface; ``inf``
        where the ray misses.  Derivatives are finite everywhere (0 where the ray misses).
    """
    shape = get_shape(kind)
    shape.require_mesh(mesh)
    return shape.ray(as_float(origin), as_float(direction), as_float(dims), t_min, mesh)


def surface_distance(kind: str, p: Array, dims: Array, mesh=None) -> Array:
    """Unsigned distance from points to the surface of one shape, in the shape's own frame.

    Parameters
    ----------
    kind : str
        The shape kind (a registered kind, :func:`mbcal.geometry.shapes.shape_kinds`); static.
    p : (..., 3) float
        Points in the shape frame.
    dims : (3,) or (..., 3) float
        The shape's dimensions; leading axes broadcast with those of ``p``.
    mesh : MeshData, optional
        The triangles of a ``mesh`` shape (static); ignored for other kinds.

    Returns
    -------
    distance : (...,) float
        Distance to the nearest point of the shape's surface (its boundary: a point inside a
        solid has a positive distance too).  Exact for every kind.  Derivatives are finite
        everywhere; where the distance has none (on the surface, on a symmetry axis, at the
        centre of a sphere) they are 0 or a one-sided value.
    """
    shape = get_shape(kind)
    shape.require_mesh(mesh)
    return shape.distance(as_float(p), as_float(dims), mesh)


# ---- scenes of several shapes ----------------------------------------------------------------------------


def _check_shapes(shape_poses: Array, shape_dims: Array, shapes: Sequence) -> None:
    n = len(shapes)
    if shape_poses.shape[-3:] != (n, 4, 4) or shape_dims.shape[-2:] != (n, 3):
        raise ValueError(
            f"{n} shapes need shape_poses (..., {n}, 4, 4) and shape_dims (..., {n}, 3); "
            f"got {tuple(shape_poses.shape)} and {tuple(shape_dims.shape)}"
        )


def _to_local(T: Array, points: Array) -> Array:
    """World points (..., n, 3) in the frame of ``T`` (..., 4, 4): R^T (p - t)."""
    # Rᵀ(p − t) as a broadcast product and sum: a matmul of 3-vectors is slow in XLA on a CPU.
    d = points - T[..., None, :3, 3]
    return jnp.sum(d[..., :, :, None] * T[..., None, :3, :3], axis=-2)


def _each_shape(shape_poses: Array, shape_dims: Array, shapes: Sequence, one: Callable[..., Array]) -> list[Array]:
    """``one(T_world_shape (..., 4, 4), dims (..., 1, 3), shape)`` for every shape, in order."""
    shape_poses, shape_dims = as_float(shape_poses), as_float(shape_dims)
    _check_shapes(shape_poses, shape_dims, shapes)
    return [one(shape_poses[..., i, :, :], shape_dims[..., i, None, :], shape) for i, shape in enumerate(shapes)]


def _nearest(per_shape: list[Array], shapes_without: tuple[tuple[int, ...], ...]) -> Array:
    """The smallest value over the shapes (last axis); ``inf`` of the broadcast of
    ``shapes_without`` when there are no shapes."""
    if not per_shape:
        return jnp.full(jnp.broadcast_shapes(*shapes_without), INF)
    return min_last(jnp.stack(jnp.broadcast_arrays(*per_shape), axis=-1))


def cast_rays(
    shape_poses: Array, shape_dims: Array, shapes: Sequence, origins: Array, directions: Array, t_min: float = 1e-9
) -> Array:
    """Cast world rays against a set of shapes: the distance to the first surface hit.

    Parameters
    ----------
    shape_poses : (..., S, 4, 4) float
        ``T_world_shape`` of each shape (rigid transforms).
    shape_dims : (..., S, 3) float
        Dimensions of each shape.
    shapes : sequence of ShapeInfo
        The S shapes' static descriptions (anything with ``kind`` and ``mesh`` attributes).
    origins, directions : (..., n, 3) float
        World rays; directions should be unit vectors (see :func:`ray_hit`).  Leading axes
        (configurations) broadcast with those of ``shape_poses``.
    t_min : float
        Hits closer than this to the origin are ignored.

    Returns
    -------
    t : (..., n) float
        The smallest hit parameter over all shapes, ``inf`` where a ray hits nothing.
    """
    origins, directions = as_float(origins), as_float(directions)

    def hit(T: Array, dims: Array, shape) -> Array:
        local = jnp.sum(directions[..., :, :, None] * T[..., None, :3, :3], axis=-2)
        return ray_hit(shape.kind, _to_local(T, origins), local, dims, shape.mesh, t_min)

    ts = _each_shape(shape_poses, shape_dims, shapes, hit)
    return _nearest(ts, (origins.shape[:-1], directions.shape[:-1], jnp.shape(shape_poses)[:-3] + (1,)))


def distance_to_shapes(shape_poses: Array, shape_dims: Array, shapes: Sequence, points: Array) -> Array:
    """Unsigned distance from world points to the nearest surface of a set of shapes.

    Parameters
    ----------
    shape_poses, shape_dims, shapes
        The shapes, as for :func:`cast_rays`.
    points : (..., n, 3) float
        World points; leading axes broadcast with those of ``shape_poses``.

    Returns
    -------
    distance : (..., n) float
        Distance to the nearest shape surface (see :func:`surface_distance`); ``inf`` when
        there are no shapes.
    """
    points = as_float(points)

    def distance(T: Array, dims: Array, shape) -> Array:
        return surface_distance(shape.kind, _to_local(T, points), dims, shape.mesh)

    ds = _each_shape(shape_poses, shape_dims, shapes, distance)
    return _nearest(ds, (points.shape[:-1], jnp.shape(shape_poses)[:-3] + (1,)))


def _select(scene, shapes: Sequence[int | str] | None):
    model = scene.model
    if shapes is None:
        index = list(range(len(model.shapes)))
    else:
        index = [s if isinstance(s, int | np.integer) else model.shape_index(s) for s in shapes]
    index_array = np.asarray(index, dtype=np.int64)
    poses = scene.shape_poses[..., index_array, :, :]
    dims = scene.shape_dims[..., index_array, :]
    return poses, dims, [model.shapes[i] for i in index]


def scene_cast_rays(
    scene, origins: Array, directions: Array, shapes: Sequence[int | str] | None = None, t_min: float = 1e-9
) -> Array:
    """:func:`cast_rays` against the shapes of a :class:`~mbcal.scene.Scene`.

    Parameters
    ----------
    scene : Scene
        A scene, or a batch of scenes (leading axes on its arrays).
    origins, directions : (..., n, 3) float
        World rays (unit directions), e.g. from ``scene.range_rays(name)``.
    shapes : sequence of int or str, optional
        The shapes to cast against, by index or (dotted suffix of their) name; all by default.
    t_min : float
        Hits closer than this to the origin are ignored.

    Returns
    -------
    t : (..., n) float
        Distance to the first surface hit, ``inf`` where a ray hits nothing.
    """
    poses, dims, infos = _select(scene, shapes)
    return cast_rays(poses, dims, infos, origins, directions, t_min)


def scene_distance(scene, points: Array, shapes: Sequence[int | str] | None = None) -> Array:
    """:func:`distance_to_shapes` for the shapes of a :class:`~mbcal.scene.Scene`.

    Parameters
    ----------
    scene : Scene
        A scene, or a batch of scenes (leading axes on its arrays).
    points : (..., n, 3) float
        World points.
    shapes : sequence of int or str, optional
        The shapes to measure to, by index or (dotted suffix of their) name; all by default.

    Returns
    -------
    distance : (..., n) float
        Distance to the nearest surface of the selected shapes.
    """
    poses, dims, infos = _select(scene, shapes)
    return distance_to_shapes(poses, dims, infos, points)
