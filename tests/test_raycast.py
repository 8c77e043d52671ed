"""Ray casting and surface distances (mbcal.geometry.raycast) against trimesh, analytic values and
finite differences."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import trimesh
from trimesh.ray.ray_triangle import RayMeshIntersector

from mbcal._jax import jax, jnp
from mbcal.geometry.raycast import (
    RAY_KINDS,
    cast_rays,
    distance_to_shapes,
    ray_hit,
    scene_cast_rays,
    scene_distance,
    surface_distance,
)
from mbcal.language import load_model_text
from mbcal.language.model import MeshData
from mbcal.modeling import modeler
from mbcal.scene import shape_mesh

SECTIONS = 720  # tessellation of the round reference meshes

DIMS = {
    "box": (0.8, 1.2, 0.6),
    "cylinder": (0.5, 1.4, 0.0),
    "cone": (0.6, 1.2, 0.0),
    "sphere": (0.7, 0.0, 0.0),
    "tube": (0.6, 0.4, 1.5),
    "rectangle": (1.2, 0.8, 0.0),
    "plane": (0.0, 0.0, 0.0),
    "mesh": (1.3, 0.9, 1.1),
}
SEED = {kind: i for i, kind in enumerate(DIMS)}
SOLIDS = ("box", "cylinder", "cone", "sphere", "tube", "mesh")

_TORUS = trimesh.creation.torus(major_radius=0.5, minor_radius=0.2, major_sections=24, minor_sections=12)
TORUS = MeshData("torus", np.asarray(_TORUS.vertices, dtype=float), np.asarray(_TORUS.faces, dtype=np.int64))


def mesh_of(kind):
    return TORUS if kind == "mesh" else None


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---- references ----------------------------------------------------------------------------------


def reference_mesh(kind, dims):
    """A fine trimesh of the shape and the largest gap between it and the true surface (its sag)."""
    dims = np.asarray(dims, dtype=float)
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=dims[0])
        sag = dims[0] - np.abs(np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles[:, 0])).min()
        return mesh, sag
    mesh = shape_mesh(kind, dims, mesh_of(kind), sections=SECTIONS, plane_size=200.0)
    sag = dims[0] * (1.0 - math.cos(math.pi / SECTIONS)) if kind in ("cylinder", "cone", "tube") else 0.0
    return mesh, sag


def reference_first_hit(mesh, origins, directions, t_min=1e-9):
    """trimesh's first hit along each ray and |cos| of the incidence angle there (1 for misses)."""
    tri, ray, loc = RayMeshIntersector(mesh).intersects_id(
        origins, directions, multiple_hits=True, return_locations=True
    )
    t = np.full(len(origins), np.inf)
    cos = np.ones(len(origins))
    if len(tri):
        s = np.einsum("ij,ij->i", loc - origins[ray], directions[ray])
        for k in np.argsort(-s):  # nearest last, so it wins
            if s[k] >= t_min:
                t[ray[k]] = s[k]
                cos[ray[k]] = abs(mesh.face_normals[tri[k]] @ directions[ray[k]])
    return t, cos


def reference_distance(mesh, points):
    """Distance from each point to the nearest of all the mesh's triangles (brute force)."""
    tri = mesh.triangles
    out = []
    for p in points:
        closest = trimesh.triangles.closest_point(tri, np.broadcast_to(p, tri.shape[:1] + (3,)))
        out.append(np.sqrt(np.min(np.sum((closest - p) ** 2, axis=1))))
    return np.array(out)


def inside(kind, p, dims, margin):
    """Points strictly inside a solid (or, for 'bore', inside a tube's bore), by ``margin``."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    rho = np.hypot(x, y)
    a, b, c = dims
    if kind == "box":
        return np.all(np.abs(p) < np.asarray(dims) / 2 - margin, axis=1)
    if kind == "sphere":
        return np.linalg.norm(p, axis=1) < a - margin
    if kind == "cylinder":
        return (rho < a - margin) & (np.abs(z) < b / 2 - margin)
    if kind == "cone":
        return (np.abs(z) < b / 2 - margin) & (rho < a * (b / 2 - z) / b - margin)
    if kind == "tube":
        return (rho > b + margin) & (rho < a - margin) & (np.abs(z) < c / 2 - margin)
    if kind == "bore":
        return (rho < b - margin) & (np.abs(z) < c / 2 - margin)
    if kind == "mesh":
        q = p / np.asarray(dims)
        return (np.hypot(q[:, 0], q[:, 1]) - 0.5) ** 2 + q[:, 2] ** 2 < (0.2 - margin) ** 2
    raise AssertionError(kind)


def sample_inside(kind, dims, n, rng, margin=0.03):
    """``n`` random points inside a solid (or a tube's bore), at least ``margin`` from its surface."""
    a, b, c = dims
    half = {
        "box": np.asarray(dims) / 2,
        "sphere": np.array([a, a, a]),
        "cylinder": np.array([a, a, b / 2]),
        "cone": np.array([a, a, b / 2]),
        "tube": np.array([a, a, c / 2]),
        "bore": np.array([b, b, c / 2]),
        "mesh": np.array([0.7, 0.7, 0.2]) * np.asarray(dims),
    }[kind]
    pts = rng.uniform(-half, half, size=(40 * n, 3))
    pts = pts[inside(kind, pts, dims, margin)]
    assert len(pts) >= n, kind
    return pts[:n]


def outside_rays(kind, dims, n, rng):
    """Rays from far away towards random points near the shape: a mix of hits and misses."""
    size = max(max(dims), 0.5)
    origins = unit(rng.normal(size=(n, 3))) * 3.0 * size
    targets = rng.uniform(-0.8 * size, 0.8 * size, size=(n, 3))
    if kind in ("rectangle", "plane"):
        targets[:, 2] = rng.uniform(-0.2, 0.2, size=n)
    directions = unit(targets - origins)
    directions[: n // 10] *= -1.0  # some point away
    return origins, directions


ray_hit_jit = jax.jit(ray_hit, static_argnames=("kind", "mesh", "t_min"))
surface_distance_jit = jax.jit(surface_distance, static_argnames=("kind", "mesh"))


def assert_hits_match(kind, dims, origins, directions):
    mesh, sag = reference_mesh(kind, dims)
    t_ref, cos = reference_first_hit(mesh, origins, directions)
    t = np.asarray(ray_hit_jit(kind, jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(dims), mesh_of(kind)))
    np.testing.assert_array_equal(np.isinf(t), np.isinf(t_ref), err_msg=f"{kind}: hits and misses differ")
    hit = np.isfinite(t)
    tol = 4.0 * sag / np.maximum(cos[hit], 1e-3) + 1e-9 * (1.0 + t_ref[hit])
    assert np.all(np.abs(t[hit] - t_ref[hit]) <= tol), f"{kind}: {np.max(np.abs(t[hit] - t_ref[hit]) - tol)}"
    return t


# ---- ray casting against trimesh -------------------------------------------------------------------


@pytest.mark.parametrize("kind", RAY_KINDS)
def test_rays_from_outside_match_trimesh_first_hit_and_misses(kind):
    rng = np.random.default_rng(SEED[kind])
    dims = DIMS[kind]
    origins, directions = outside_rays(kind, dims, 300, rng)
    if kind == "plane":  # keep rays whose hit lies on the (finite) reference square
        t_plane = -origins[:, 2] / directions[:, 2]
        far = (t_plane > 0) & (np.abs(origins[:, :2] + t_plane[:, None] * directions[:, :2]) > 90).any(axis=1)
        origins, directions = origins[~far], directions[~far]
    t = assert_hits_match(kind, dims, origins, directions)
    assert 0.2 < np.isfinite(t).mean() < 1.0  # the rays exercise both hits and misses


@pytest.mark.parametrize("kind", SOLIDS)
def test_rays_from_inside_a_solid_hit_its_boundary_like_trimesh(kind):
    rng = np.random.default_rng(10 + SEED[kind])
    dims = DIMS[kind]
    origins = sample_inside(kind, dims, 200, rng)
    directions = unit(rng.normal(size=(200, 3)))
    t = assert_hits_match(kind, dims, origins, directions)
    assert np.all(np.isfinite(t))  # nothing escapes from inside a closed solid


def test_rays_from_a_tube_bore_hit_the_inner_wall_or_leave_through_the_ends():
    rng = np.random.default_rng(7)
    dims = DIMS["tube"]
    origins = sample_inside("bore", dims, 200, rng)
    directions = unit(rng.normal(size=(200, 3)))
    t = assert_hits_match("tube", dims, origins, directions)
    assert np.isfinite(t).any() and np.isinf(t).any()


def test_ray_through_tube_bore_hits_inner_wall():
    outer, inner, length = DIMS["tube"]
    t = ray_hit("tube", jnp.array([0.1, 0.0, 0.0]), jnp.array([1.0, 0.0, 0.0]), jnp.array(DIMS["tube"]))
    np.testing.assert_allclose(t, inner - 0.1, rtol=1e-14)
    # from outside, through the wall: the outer surface first
    t = ray_hit("tube", jnp.array([-2.0, 0.0, 0.0]), jnp.array([1.0, 0.0, 0.0]), jnp.array(DIMS["tube"]))
    np.testing.assert_allclose(t, 2.0 - outer, rtol=1e-14)
    # along the axis through the bore: nothing; parallel to the axis through the wall: the end face
    t = ray_hit(
        "tube", jnp.array([[0.0, 0.0, -3.0], [0.5, 0.0, -3.0]]), jnp.array([0.0, 0.0, 1.0]), jnp.array(DIMS["tube"])
    )
    np.testing.assert_allclose(t, [np.inf, 3.0 - length / 2], rtol=1e-14)


def test_mesh_hits_are_exact_and_scale_with_dims():
    o = jnp.array([0.0, 0.0, 3.0])
    d = jnp.array([0.0, 0.0, -1.0])
    tri = MeshData("tri", np.array([[-1.0, -1.0, 0.5], [1.0, -1.0, 0.5], [0.0, 1.0, 0.5]]), np.array([[0, 1, 2]]))
    np.testing.assert_allclose(ray_hit("mesh", o, d, jnp.ones(3), tri), 2.5, rtol=1e-15)
    np.testing.assert_allclose(ray_hit("mesh", o, d, jnp.array([1.0, 1.0, 2.0]), tri), 2.0, rtol=1e-15)
    assert np.isinf(ray_hit("mesh", o, -d, jnp.ones(3), tri))  # behind the origin
    assert np.isinf(ray_hit("mesh", jnp.array([0.0, 0.0, 0.5]), jnp.array([1.0, 0.0, 0.0]), jnp.ones(3), tri))


def test_mesh_kernels_broadcast_over_batched_dims_and_vmap():
    rng = np.random.default_rng(5)
    dims = np.array([[[1.0, 1.0, 1.0]], [[1.3, 0.9, 1.1]], [[0.8, 1.2, 1.5]]])  # (3 configurations, 1, 3)
    origins, directions = outside_rays("mesh", DIMS["mesh"], 40, rng)
    points = rng.uniform(-1.0, 1.0, size=(40, 3))
    for f, args in ((ray_hit_jit, (origins, directions)), (surface_distance_jit, (points,))):
        loop = np.stack([np.asarray(f("mesh", *args, dims[b, 0], TORUS)) for b in range(3)])
        assert np.isfinite(loop).any()
        np.testing.assert_allclose(np.asarray(f("mesh", *args, dims, TORUS)), loop, rtol=1e-14)
        mapped = jax.vmap(lambda D, f=f, args=args: f("mesh", *args, D, TORUS))(jnp.asarray(dims[:, 0]))
        np.testing.assert_allclose(np.asarray(mapped), loop, rtol=1e-14)


def test_analytic_hits_of_every_primitive():
    z = jnp.array([0.0, 0.0, 1.0])
    below = jnp.array([0.0, 0.0, -5.0])
    cases = {
        "box": 5.0 - 0.3,
        "cylinder": 5.0 - 0.7,
        "cone": 5.0 - 0.6,
        "sphere": 5.0 - 0.7,
        "tube": np.inf,  # straight up the bore
        "rectangle": 5.0,
        "plane": 5.0,
    }
    for kind, expected in cases.items():
        np.testing.assert_allclose(ray_hit(kind, below, z, jnp.array(DIMS[kind])), expected, rtol=1e-14, err_msg=kind)
    # from the centre of each solid, along the axis: the far side
    centre = jnp.zeros(3)
    for kind, expected in {"box": 0.3, "cylinder": 0.7, "cone": 0.6, "sphere": 0.7}.items():
        np.testing.assert_allclose(ray_hit(kind, centre, z, jnp.array(DIMS[kind])), expected, rtol=1e-14, err_msg=kind)
    # the cone's slant side from the axis: radius at z = 0 is R / 2
    t = ray_hit("cone", centre, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.6, 1.2, 0.0]))
    np.testing.assert_allclose(t, 0.3, rtol=1e-14)


def test_rectangle_and_plane_are_two_sided_and_parallel_rays_miss():
    dims = jnp.array(DIMS["rectangle"])
    for kind in ("rectangle", "plane"):
        up = ray_hit(kind, jnp.array([0.1, 0.2, -2.0]), jnp.array([0.0, 0.0, 1.0]), dims)
        down = ray_hit(kind, jnp.array([0.1, 0.2, 2.0]), jnp.array([0.0, 0.0, -1.0]), dims)
        np.testing.assert_allclose([up, down], [2.0, 2.0], rtol=1e-15)
        for z0 in (0.0, 1.0):
            assert np.isinf(ray_hit(kind, jnp.array([-3.0, 0.0, z0]), jnp.array([1.0, 0.0, 0.0]), dims))
    assert np.isinf(ray_hit("rectangle", jnp.array([1.0, 0.0, 2.0]), jnp.array([0.0, 0.0, -1.0]), dims))


def test_rays_starting_on_a_surface_ignore_it():
    dims = jnp.array(DIMS["sphere"])
    on = jnp.array([0.0, 0.0, 0.7])
    assert np.isinf(ray_hit("sphere", on, jnp.array([0.0, 0.0, 1.0]), dims))  # leaving: nothing
    np.testing.assert_allclose(ray_hit("sphere", on, jnp.array([0.0, 0.0, -1.0]), dims), 1.4, rtol=1e-14)
    wall = jnp.array(DIMS["rectangle"])
    assert np.isinf(ray_hit("rectangle", jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]), wall))
    # t_min can be raised to skip hits near the origin
    assert np.isinf(ray_hit("sphere", jnp.array([0.0, 0.0, -1.0]), jnp.array([0.0, 0.0, 1.0]), dims, t_min=2.0))


def test_t_is_the_ray_parameter_so_unit_directions_give_distances():
    for kind in RAY_KINDS:
        o = jnp.array([0.5, 0.05, -5.0] if kind in ("tube", "mesh") else [0.05, 0.05, -5.0])
        d = jnp.array([0.01, -0.005, 1.0])
        t1 = ray_hit(kind, o, d, jnp.array(DIMS[kind]), mesh_of(kind))
        t2 = ray_hit(kind, o, 2.0 * d, jnp.array(DIMS[kind]), mesh_of(kind))
        assert np.isfinite(t1), kind
        np.testing.assert_allclose(t2, t1 / 2.0, rtol=1e-13, err_msg=kind)
        assert np.isinf(ray_hit(kind, o, jnp.zeros(3), jnp.array(DIMS[kind]), mesh_of(kind)))


def test_unknown_kinds_and_missing_meshes_are_errors():
    with pytest.raises(ValueError, match="unknown shape kind"):
        ray_hit("torus", jnp.zeros(3), jnp.ones(3), jnp.ones(3))
    with pytest.raises(ValueError, match="MeshData"):
        surface_distance("mesh", jnp.zeros(3), jnp.ones(3))


# ---- surface distance ------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", RAY_KINDS)
def test_surface_distance_matches_brute_force_over_a_fine_mesh_inside_and_outside(kind):
    rng = np.random.default_rng(20 + SEED[kind])
    dims = DIMS[kind]
    size = max(max(dims), 0.5)
    points = rng.uniform(-1.2 * size, 1.2 * size, size=(150, 3))
    if kind in SOLIDS:
        points = np.concatenate([points, sample_inside(kind, dims, 50, rng, margin=0.0)])
    if kind == "tube":
        points = np.concatenate([points, sample_inside("bore", dims, 50, rng, margin=0.0)])
    mesh, sag = reference_mesh(kind, dims)
    d_ref = reference_distance(mesh, points)
    d = np.asarray(surface_distance_jit(kind, jnp.asarray(points), jnp.asarray(dims), mesh_of(kind)))
    np.testing.assert_allclose(d, d_ref, atol=sag + 1e-9, rtol=0)


def test_surface_distance_analytic_values():
    centre = jnp.zeros(3)
    np.testing.assert_allclose(surface_distance("sphere", centre, jnp.array(DIMS["sphere"])), 0.7, rtol=1e-15)
    np.testing.assert_allclose(surface_distance("box", centre, jnp.array(DIMS["box"])), 0.3, rtol=1e-15)
    np.testing.assert_allclose(surface_distance("cylinder", centre, jnp.array(DIMS["cylinder"])), 0.5, rtol=1e-15)
    np.testing.assert_allclose(surface_distance("tube", centre, jnp.array(DIMS["tube"])), 0.4, rtol=1e-15)
    # a tube without a bore is a cylinder
    p = jnp.array([0.05, 0.0, 0.1])
    np.testing.assert_allclose(
        surface_distance("tube", p, jnp.array([0.5, 0.0, 1.4])),
        surface_distance("cylinder", p, jnp.array(DIMS["cylinder"])),
    )
    # cone: from the centre, perpendicular to the slant side, which is nearer than the base
    R, L = 0.6, 1.2
    expected = min(L / 2, (R / 2) * L / math.hypot(R, L))
    np.testing.assert_allclose(surface_distance("cone", centre, jnp.array([R, L, 0.0])), expected, rtol=1e-14)
    np.testing.assert_allclose(surface_distance("plane", jnp.array([3.0, -4.0, -0.25]), jnp.zeros(3)), 0.25)
    np.testing.assert_allclose(
        surface_distance("rectangle", jnp.array([1.0, 0.0, 0.3]), jnp.array(DIMS["rectangle"])), 0.5, rtol=1e-15
    )


def test_surface_distance_to_a_triangle_in_every_voronoi_region():
    tri = MeshData("tri", np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([[0, 1, 2]]))
    cases = {
        (0.2, 0.2, 0.5): 0.5,  # face
        (-1.0, -1.0, 0.0): math.sqrt(2.0),  # vertex a
        (2.0, -1.0, 0.0): math.sqrt(2.0),  # vertex b
        (-1.0, 2.0, 0.0): math.sqrt(2.0),  # vertex c
        (0.5, -1.0, 1.0): math.sqrt(2.0),  # edge ab
        (-1.0, 0.5, 0.0): 1.0,  # edge ac
        (1.0, 1.0, 0.0): math.sqrt(0.5),  # edge bc
    }
    for p, expected in cases.items():
        np.testing.assert_allclose(surface_distance("mesh", jnp.array(p), jnp.ones(3), tri), expected, rtol=1e-14)


# ---- derivatives -----------------------------------------------------------------------------------


def central_jacobian(f, args, which, h=1e-6):
    """Central differences of ``f(*args)`` w.r.t. ``args[which]`` (shape of f's value + shape of that arg)."""
    args = [np.asarray(x, dtype=float) for x in args]
    x = args[which]
    cols = []
    for k in range(x.size):
        e = np.zeros(x.size)
        e[k] = h
        plus, minus = list(args), list(args)
        plus[which] = x + e.reshape(x.shape)
        minus[which] = x - e.reshape(x.shape)
        cols.append((np.asarray(f(*plus)) - np.asarray(f(*minus))) / (2 * h))
    return np.stack(cols, axis=-1).reshape(np.shape(f(*args)) + x.shape)


@functools.partial(jax.jit, static_argnames=("kind", "mesh"))
def hit_jacobians(kind, o, d, dims, mesh=None):
    """Forward- and reverse-mode Jacobians of ray_hit w.r.t. origin, direction and dims (6 blocks)."""

    def f(o, d, dims):
        return ray_hit(kind, o, d, dims, mesh)

    return jax.jacfwd(f, argnums=(0, 1, 2))(o, d, dims) + jax.jacrev(f, argnums=(0, 1, 2))(o, d, dims)


@functools.partial(jax.jit, static_argnames=("kind", "mesh"))
def distance_jacobians(kind, p, dims, mesh=None):
    """Forward- and reverse-mode Jacobians of surface_distance w.r.t. the point and dims (4 blocks)."""

    def f(p, dims):
        return surface_distance(kind, p, dims, mesh)

    return jax.jacfwd(f, argnums=(0, 1))(p, dims) + jax.jacrev(f, argnums=(0, 1))(p, dims)


# Rays that hit a smooth part of each surface (away from edges and rims).
SMOOTH_HITS = {
    "box": [((0.1, 0.2, -2.0), (0.1, -0.05, 1.0)), ((0.1, 0.1, 0.0), (1.0, 0.3, 0.2))],
    "cylinder": [
        ((-3.0, 0.1, 0.2), (1.0, 0.05, 0.03)),
        ((0.1, 0.1, -3.0), (0.02, 0.01, 1.0)),
        ((0.0, 0.1, 0.0), (1.0, 0.2, 0.1)),
    ],
    "cone": [
        ((-3.0, 0.05, -0.1), (1.0, 0.02, 0.05)),
        ((0.1, 0.0, -3.0), (0.03, 0.02, 1.0)),
        ((0.0, 0.0, 0.0), (1.0, 0.1, 0.2)),
    ],
    "sphere": [((0.2, 0.1, -3.0), (0.05, 0.02, 1.0)), ((0.1, 0.0, 0.1), (0.3, 1.0, -0.2))],
    "tube": [
        ((-3.0, 0.1, 0.2), (1.0, 0.05, 0.03)),
        ((0.1, 0.0, 0.3), (1.0, 0.2, 0.1)),
        ((0.5, 0.0, -3.0), (0.01, 0.02, 1.0)),
    ],
    "rectangle": [((0.1, 0.2, 2.0), (0.05, -0.02, -1.0))],
    "plane": [((1.0, 2.0, 3.0), (0.3, 0.1, -1.0))],
    "mesh": [((0.61, 0.07, 2.0), (0.013, -0.021, -1.0)), ((0.0, 0.0, 0.02), (1.0, 0.17, 0.05))],
}


@pytest.mark.parametrize("kind", RAY_KINDS)
def test_hit_distance_jacobians_match_central_differences(kind):
    mesh = mesh_of(kind)

    def f(o, d, dims):
        return ray_hit_jit(kind, jnp.asarray(o), jnp.asarray(d), jnp.asarray(dims), mesh)

    for o, d in SMOOTH_HITS[kind]:
        args = [np.asarray(o, dtype=float), unit(d), np.asarray(DIMS[kind], dtype=float)]
        assert np.isfinite(f(*args))
        blocks = hit_jacobians(kind, *map(jnp.asarray, args), mesh=mesh)
        for which in range(3):
            fd = central_jacobian(f, args, which)
            for J in (blocks[which], blocks[3 + which]):  # forward and reverse mode
                np.testing.assert_allclose(np.asarray(J), fd, rtol=1e-6, atol=1e-7, err_msg=f"{kind} {o} arg {which}")


@pytest.mark.parametrize("kind", RAY_KINDS)
def test_surface_distance_jacobians_match_central_differences(kind):
    rng = np.random.default_rng(3)
    mesh = mesh_of(kind)

    def f(p, dims):
        return surface_distance_jit(kind, jnp.asarray(p), jnp.asarray(dims), mesh)

    for p in (rng.uniform(-1.0, 1.0, 3), rng.uniform(-0.2, 0.2, 3)):
        args = [p, np.asarray(DIMS[kind], dtype=float)]
        blocks = distance_jacobians(kind, *map(jnp.asarray, args), mesh=mesh)
        for which in range(2):
            fd = central_jacobian(f, args, which)
            for J in (blocks[which], blocks[2 + which]):
                np.testing.assert_allclose(np.asarray(J), fd, rtol=1e-6, atol=1e-7, err_msg=f"{kind} {p} arg {which}")


DEGENERATE_RAYS = [
    ("sphere", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # through the centre
    ("sphere", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # from the centre
    ("sphere", (0.7, 0.0, -3.0), (0.0, 0.0, 1.0)),  # grazing
    ("sphere", (2.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # miss
    ("box", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # parallel to four faces
    ("box", (3.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # miss, parallel
    ("box", (0.4, 0.6, -3.0), (0.0, 0.0, 1.0)),  # along an edge
    ("cylinder", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # along the axis
    ("cylinder", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # along the axis from inside
    ("cylinder", (0.0, 2.0, 0.0), (1.0, 0.0, 0.0)),  # miss, perpendicular
    ("cone", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # along the axis
    ("cone", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),  # out through the apex
    ("cone", (0.0, 0.0, 3.0), (0.0, 0.0, -1.0)),  # in through the apex
    ("cone", (0.3, 0.0, 0.0), (-1.0, 0.0, 2.0)),  # parallel to a generator line
    ("tube", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # along the axis, through the bore
    ("tube", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # from the axis
    ("tube", (3.0, 3.0, 0.0), (1.0, 0.0, 0.0)),  # miss
    ("rectangle", (-3.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # in its plane
    ("rectangle", (-3.0, 0.0, 1.0), (1.0, 0.0, 0.0)),  # parallel above it
    ("plane", (0.0, 0.0, 1.0), (1.0, 0.0, 0.0)),  # parallel
    ("mesh", (-3.0, 0.0, 0.0), (1.0, 0.0, 0.0)),  # in the torus's plane of symmetry
    ("mesh", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0)),  # through the hole
    ("mesh", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # no direction
]


@pytest.mark.parametrize(("kind", "o", "d"), DEGENERATE_RAYS)
def test_hit_derivatives_are_finite_for_misses_and_degenerate_rays(kind, o, d):
    args = (jnp.array(o, dtype=float), jnp.array(d, dtype=float), jnp.array(DIMS[kind]))
    for block in hit_jacobians(kind, *args, mesh=mesh_of(kind)):
        assert np.all(np.isfinite(np.asarray(block))), (kind, o, d)


def test_degenerate_rays_still_hit_where_they_should():
    t = {
        (k, o, d): float(ray_hit(k, jnp.array(o), jnp.array(d), jnp.array(DIMS[k]), mesh_of(k)))
        for k, o, d in DEGENERATE_RAYS
    }
    assert t[("sphere", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0))] == pytest.approx(2.3)
    assert t[("box", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0))] == pytest.approx(2.7)
    assert t[("cylinder", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))] == pytest.approx(0.7)
    assert t[("cone", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))] == pytest.approx(0.6)  # the apex
    assert t[("cone", (0.0, 0.0, 3.0), (0.0, 0.0, -1.0))] == pytest.approx(2.4)
    assert t[("tube", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))] == pytest.approx(0.4)
    assert math.isinf(t[("tube", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0))])
    assert math.isinf(t[("mesh", (0.0, 0.0, -3.0), (0.0, 0.0, 1.0))])


DEGENERATE_POINTS = [
    ("sphere", (0.0, 0.0, 0.0)),  # the centre
    ("sphere", (0.0, 0.0, 0.7)),  # on the surface
    ("box", (0.0, 0.0, 0.0)),
    ("box", (0.4, 0.6, 0.3)),  # a corner
    ("cylinder", (0.0, 0.0, 0.0)),
    ("cylinder", (0.0, 0.0, 2.0)),  # on the axis, outside
    ("cone", (0.0, 0.0, 0.6)),  # the apex
    ("cone", (0.0, 0.0, 0.0)),
    ("tube", (0.0, 0.0, 0.0)),
    ("tube", (0.0, 0.0, 3.0)),
    ("rectangle", (0.0, 0.0, 0.0)),
    ("rectangle", (0.6, 0.4, 0.0)),
    ("plane", (0.0, 0.0, 0.0)),
    ("mesh", (0.0, 0.0, 0.0)),
    ("mesh", tuple(np.asarray(TORUS.vertices[0]) * DIMS["mesh"])),  # a vertex
]


@pytest.mark.parametrize(("kind", "p"), DEGENERATE_POINTS)
def test_distance_derivatives_are_finite_at_centres_axes_and_on_surfaces(kind, p):
    args = (jnp.array(p, dtype=float), jnp.array(DIMS[kind]))
    for block in distance_jacobians(kind, *args, mesh=mesh_of(kind)):
        assert np.all(np.isfinite(np.asarray(block))), (kind, p)


# ---- scenes ----------------------------------------------------------------------------------------------

SCENE_TEXT = """
param wall.y = 2 m
param ball.y = 1 m
shape wall = rectangle(2 m, 1.6 m) at translate(0, wall.y, 0) * rot_x(90 deg)
frame ball at translate(0.05 m, ball.y, 0) {
  shape s = sphere(10 cm)
  shape stem = cylinder(1 cm, 30 cm) at translate(0, 0, -25 cm)
}
frame sensor {
  range scanner(directions = [(0.05, 1, 0), (0.09, 1, 0.02), (0.3, 1, 0), (0, 1, -0.3), (2, 1, 0), (0, -1, 0),
                               (0.05, 1, -0.25)])
}
"""


@pytest.fixture(scope="module")
def wall_and_ball():
    model = load_model_text(SCENE_TEXT)
    return model, modeler(model, model.nominal)


def test_nearest_surface_wins_a_ball_in_front_of_a_wall(wall_and_ball):
    model, scene = wall_and_ball
    origins, directions = scene.range_rays("scanner")
    t = np.asarray(cast_rays(scene.shape_poses, scene.shape_dims, model.shapes, origins, directions))
    np.testing.assert_allclose(t, np.asarray(scene_cast_rays(scene, origins, directions)))
    d = np.asarray(directions)
    np.testing.assert_allclose(t[0], math.hypot(1.0, 0.05) - 0.1, rtol=1e-12)  # the ball's near side
    np.testing.assert_allclose(t[2], 2.0 / d[2, 1], rtol=1e-12)  # past the ball: the wall
    np.testing.assert_allclose(t[3], 2.0 / d[3, 1], rtol=1e-12)  # under the ball, past the stem: the wall
    assert np.isinf(t[4]) and np.isinf(t[5])  # beside the wall; backwards
    np.testing.assert_allclose(t[6] * np.hypot(d[6, 0], d[6, 1]), math.hypot(0.05, 1.0) - 0.01, rtol=1e-12)  # the stem
    # trimesh on the exported scene agrees (its sphere is an icosphere: compare to its sag)
    reference = scene.to_trimesh().to_mesh()
    t_ref, cos = reference_first_hit(reference, np.asarray(origins), d)
    np.testing.assert_array_equal(np.isinf(t), np.isinf(t_ref))
    hit = np.isfinite(t)
    np.testing.assert_allclose(t[hit], t_ref[hit], atol=3e-3)
    # only the wall: the ball is transparent
    t_wall = np.asarray(scene_cast_rays(scene, origins, directions, shapes=["wall"]))
    np.testing.assert_allclose(t_wall[0], 2.0 / d[0, 1], rtol=1e-12)


@pytest.mark.slow
def test_range_to_a_wall_follows_the_wall_parameter_one_for_one(wall_and_ball):
    model, _ = wall_and_ball
    i = model.param_index("wall.y")

    def ranges(x):
        scene = modeler(model, x)
        return scene_cast_rays(scene, *scene.range_rays("scanner"))

    J = np.asarray(jax.jacfwd(ranges)(jnp.asarray(model.nominal)))
    assert np.all(np.isfinite(J))
    d = np.asarray(modeler(model, model.nominal).range_rays("scanner")[1])
    np.testing.assert_allclose(J[2, i], 1.0 / d[2, 1], rtol=1e-12)  # wall hit
    np.testing.assert_allclose(J[0, i], 0.0, atol=1e-15)  # ball hit
    np.testing.assert_allclose(J[4:6, :], 0.0)  # misses


def test_cast_rays_pose_and_dims_jacobians_match_central_differences(wall_and_ball):
    model, scene = wall_and_ball
    origins = jnp.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.01], [0.3, 0.0, 0.1], [0.05, 1.0, -0.6]])
    directions = jnp.asarray(unit([[0.05, 1.0, 0.0], [0.06, 1.0, 0.03], [0.1, 1.0, 0.1], [0.01, 0.02, 1.0]]))
    poses, dims = np.asarray(scene.shape_poses), np.asarray(scene.shape_dims)

    @jax.jit
    def f(P, D, O):
        return cast_rays(P, D, model.shapes, O, directions)

    args = [poses, dims, np.asarray(origins)]
    assert np.all(np.isfinite(np.asarray(f(*args))))
    blocks = jax.jit(jax.jacfwd(f, argnums=(0, 1, 2)))(*args)
    for which in range(3):
        np.testing.assert_allclose(np.asarray(blocks[which]), central_jacobian(f, args, which), atol=1e-7)


def test_distance_to_shapes_is_the_nearest_surface(wall_and_ball):
    model, scene = wall_and_ball
    points = jnp.array([[0.05, 1.0, 0.3], [0.05, 1.0, 0.0], [0.05, 1.7, 0.0], [5.0, 2.0, 0.0], [0.05, 1.0, -0.2]])
    d = np.asarray(distance_to_shapes(scene.shape_poses, scene.shape_dims, model.shapes, points))
    np.testing.assert_allclose(d, [0.2, 0.1, 0.3, math.hypot(4.0, 0.0), 0.01], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(scene_distance(scene, points)), d)
    np.testing.assert_allclose(
        np.asarray(scene_distance(scene, points, shapes=[1])), [0.2, 0.1, 0.6, np.hypot(4.95, 1.0) - 0.1, 0.1]
    )
    # brute force: trimesh's closest point on the exported scene
    ref = reference_distance(scene.to_trimesh().to_mesh(), np.asarray(points))
    np.testing.assert_allclose(d, ref, atol=3e-3)


@pytest.mark.slow
def test_batched_configurations_match_vmap_and_jit(wall_and_ball):
    model, _ = wall_and_ball
    xs = np.stack([model.nominal + [0.1 * k, -0.05 * k] for k in range(3)])
    scenes = [modeler(model, x) for x in xs]
    batch = jax.vmap(lambda x: modeler(model, x))(jnp.asarray(xs))
    origins, directions = batch.range_rays("scanner")  # (3, n, 3)
    expected = np.stack([np.asarray(scene_cast_rays(s, *s.range_rays("scanner"))) for s in scenes])
    np.testing.assert_allclose(np.asarray(scene_cast_rays(batch, origins, directions)), expected, rtol=1e-14)
    fast = jax.jit(cast_rays, static_argnames=("shapes", "t_min"))
    mapped = jax.vmap(lambda P, D, o, d: fast(P, D, model.shapes, o, d))(
        batch.shape_poses, batch.shape_dims, origins, directions
    )
    np.testing.assert_allclose(np.asarray(mapped), expected, rtol=1e-14)
    points = origins + 0.5 * directions
    dist = np.stack([np.asarray(scene_distance(s, points[k])) for k, s in enumerate(scenes)])
    np.testing.assert_allclose(np.asarray(scene_distance(batch, points)), dist, rtol=1e-14)


def test_shape_count_mismatch_and_empty_shape_lists():
    with pytest.raises(ValueError, match="2 shapes"):
        cast_rays(jnp.zeros((1, 4, 4)), jnp.zeros((1, 3)), [None, None], jnp.zeros((1, 3)), jnp.ones((1, 3)))
    t = cast_rays(jnp.zeros((0, 4, 4)), jnp.zeros((0, 3)), [], jnp.zeros((4, 3)), jnp.ones((4, 3)))
    assert t.shape == (4,) and np.all(np.isinf(np.asarray(t)))
    d = distance_to_shapes(jnp.zeros((0, 4, 4)), jnp.zeros((0, 3)), [], jnp.zeros((4, 3)))
    assert d.shape == (4,) and np.all(np.isinf(np.asarray(d)))


@pytest.mark.slow
def test_jitted_derivative_of_the_nearest_of_several_shapes_is_finite():
    # Regression: jnp.min's derivative compares inputs with the result for equality; inside jit
    # XLA rounding made that fail for some points, giving 0/0.  Selection by argmin does not.
    model = load_model_text(
        "object valve at (0, 0.74 m, 1.05 m) {\n"
        "  shape body = cylinder(3.5 cm, 7 cm) at rot_x(90 deg)\n"
        "  shape arm = box(2.5 cm, 1.5 cm, 25 cm) at (0, -4.5 cm, 12.5 cm)\n"
        "  shape knob = sphere(2 cm) at (0, -4.5 cm, 25 cm)\n"
        "}\n"
    )
    scene = modeler(model, model.nominal)
    points = jnp.asarray(np.random.default_rng(0).uniform([-0.4, 0.4, 0.8], [0.4, 0.9, 1.4], (64, 3)))
    shapes = list(model.shapes)

    def f(t):
        poses = scene.shape_poses.at[:, 0, 3].add(t)
        return distance_to_shapes(poses, scene.shape_dims, shapes, points)

    jitted = np.asarray(jax.jit(jax.jacfwd(f))(0.0))
    eager = np.asarray(jax.jacfwd(f)(0.0))
    assert np.all(np.isfinite(jitted))
    np.testing.assert_allclose(jitted, eager, atol=1e-12)
