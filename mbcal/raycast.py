"""Differentiable ray casting and point-to-surface distances for the scene's shapes.

Two measurement models rest on these kernels: a range sensor (the distance along a ray to the
first surface of the scene) and point-to-surface distance.  Everything is written in JAX
(float64), works under ``jit`` and ``vmap``, and has finite derivatives everywhere: every
square root, norm and division that can meet zero is guarded with the "double where" pattern
(the unsafe input is replaced before the operation, the result is selected after it), so rays
that miss, rays parallel to a face and points on an axis give derivative 0 rather than NaN.
Where a ray hits a smooth part of a surface, the derivative is that of the hit distance.

Every primitive is centred on its own frame's origin with its axis along z (see
:data:`mbcal.language.model.SHAPE_KINDS`); ``dims`` is a length-3 array, zero-padded:

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

from collections.abc import Sequence
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp

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

RAY_KINDS: tuple[str, ...] = ("box", "cylinder", "cone", "sphere", "tube", "rectangle", "plane", "mesh")

# A component of a direction smaller than this fraction of its length (squared: 1e-24) counts
# as zero: the ray is parallel to the face or axis it belongs to.  This keeps 1/d finite.
_PARALLEL = 1e-24
# Relative slack of the boundary tests where two surfaces of one shape meet (rims, mesh
# edges), so that rays through a seam are not lost between the two.
_EDGE = 1e-12
_INF = float("inf")


# ---- guarded elementary operations ----------------------------------------------------------------


def _safe_div(num: Array, den: Array, ok: Array) -> Array:
    """``num / den`` where ``ok``, 0 elsewhere; derivatives stay finite where ``den`` is 0."""
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), 0.0)


def _safe_sqrt(x: Array) -> Array:
    """``sqrt(x)`` for x > 0, 0 elsewhere, with derivative 0 (not inf or NaN) at and below 0."""
    ok = x > 0.0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


# Minima and maxima by selection, not by jnp.min/jnp.minimum: JAX differentiates those by
# comparing each input with the result for equality, and inside jit XLA may compute the two
# with different rounding (fused multiply-adds), so nothing matches and the derivative is
# lost — or, for reductions, becomes 0/0.  A selection keeps value and derivative together.


def _minimum(a: Array, b: Array) -> Array:
    return jnp.where(a <= b, a, b)


def _maximum(a: Array, b: Array) -> Array:
    return jnp.where(a >= b, a, b)


def _min_last(x: Array) -> Array:
    i = jnp.argmin(x, axis=-1)
    return jnp.take_along_axis(x, i[..., None], axis=-1)[..., 0]


def _max_last(x: Array) -> Array:
    i = jnp.argmax(x, axis=-1)
    return jnp.take_along_axis(x, i[..., None], axis=-1)[..., 0]


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _as_float(x: Array) -> Array:
    return jnp.asarray(x, dtype=jnp.float64)


def _check_kind(kind: str, mesh) -> None:
    if kind not in RAY_KINDS:
        raise ValueError(f"unknown shape kind '{kind}' (expected one of {', '.join(RAY_KINDS)})")
    if kind == "mesh" and mesh is None:
        raise ValueError("a 'mesh' shape needs its MeshData (vertices and faces)")


def _mesh_triangles(mesh) -> np.ndarray:
    """The mesh's unscaled triangles (f, 3, 3) as a numpy constant."""
    return np.asarray(mesh.vertices, dtype=float)[np.asarray(mesh.faces, dtype=np.int64)]


# Meshes are evaluated on 3-vectors held as tuples of their components, so that XLA fuses the
# whole (rays x triangles) computation into one loop instead of materialising (n, f, 3) arrays.


def _components(v: Array, expand: bool = False) -> tuple[Array, Array, Array]:
    if expand:
        return v[..., 0, None], v[..., 1, None], v[..., 2, None]
    return v[..., 0], v[..., 1], v[..., 2]


def _tsub(a, b):
    return a[0] - b[0], a[1] - b[1], a[2] - b[2]


def _tdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _tcross(a, b):
    return a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]


def _tlerp(a, s, e):
    """a + s * e."""
    return a[0] + s * e[0], a[1] + s * e[1], a[2] + s * e[2]


def _tselect(mask, a, b):
    return tuple(jnp.where(mask, x, y) for x, y in zip(a, b))


def _triangle_components(tri: Array):
    """Vertices a, b, c of triangles (..., 3, 3) as component tuples."""
    return _components(tri[..., 0, :]), _components(tri[..., 1, :]), _components(tri[..., 2, :])


# ---- ray casting: helpers ---------------------------------------------------------------------------


def _quadratic_roots(A: Array, B: Array, C: Array, a_ok: Array):
    """Real roots of ``A t² + 2 B t + C = 0`` without cancellation.

    Returns ``(t1, t2, ok1, ok2)``.  Where ``a_ok`` is false, A is taken as 0 and the only
    root is the linear one, in ``t2``.  A double root (zero discriminant: a grazing ray, or a
    ray through the apex of a cone) counts, with the derivative of the square root taken as 0.
    """
    A = jnp.where(a_ok, A, 0.0)
    disc = B * B - A * C
    s = _safe_sqrt(disc)
    q = -(B + jnp.where(B >= 0.0, s, -s))
    ok = (disc >= 0.0) & (q != 0.0)
    t2 = _safe_div(C, q, ok)
    ok1 = ok & a_ok
    t1 = _safe_div(q, A, ok1)
    return t1, t2, ok1, ok


def _first_hit(ts: Sequence[Array], oks: Sequence[Array], t_min: float) -> Array:
    """The smallest candidate ``t >= t_min`` that is valid; inf where there is none."""
    ts = jnp.broadcast_arrays(*ts)
    oks = jnp.broadcast_arrays(*oks)
    t = jnp.stack(ts, axis=-1)
    ok = jnp.stack(oks, axis=-1) & (t >= t_min)
    return _min_last(jnp.where(ok, t, _INF))


def _slab(o: Array, d: Array, half: Array, dd: Array):
    """Entry and exit parameters (lo, hi) of a ray in the slab |coordinate| <= half.

    A ray parallel to the slab is inside it for every t (lo = -inf, hi = inf) or never
    (lo = inf, hi = -inf).
    """
    par = d * d <= _PARALLEL * dd
    t1 = _safe_div(-half - o, d, ~par)
    t2 = _safe_div(half - o, d, ~par)
    inside = jnp.abs(o) <= half
    lo = jnp.where(par, jnp.where(inside, -_INF, _INF), _minimum(t1, t2))
    hi = jnp.where(par, jnp.where(inside, _INF, -_INF), _maximum(t1, t2))
    return lo, hi


def _interval_hit(near: Array, far: Array, t_min: float) -> Array:
    """First boundary crossing of a ray whose part inside a convex solid is [near, far]."""
    t = jnp.where(near >= t_min, near, far)
    ok = (near <= far) & (t >= t_min) & (t < _INF)
    return jnp.where(ok, t, _INF)


# ---- ray casting: one kind each ---------------------------------------------------------------------


def _ray_box(o, d, dims, t_min):
    dd = _dot(d, d)[..., None]
    lo, hi = _slab(o, d, dims / 2.0, dd)
    return _interval_hit(_max_last(lo), _min_last(hi), t_min)


def _ray_sphere(o, d, dims, t_min):
    r = dims[..., 0]
    A = _dot(d, d)
    t1, t2, ok1, ok2 = _quadratic_roots(A, _dot(o, d), _dot(o, o) - r * r, A > 0.0)
    return _first_hit([t1, t2], [ok1, ok2], t_min)


def _ray_cylinder(o, d, dims, t_min):
    r, length = dims[..., 0], dims[..., 1]
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    dd = _dot(d, d)
    A = dx * dx + dy * dy
    C = ox * ox + oy * oy - r * r
    a_ok = A > _PARALLEL * dd
    t1, t2, ok, _ = _quadratic_roots(A, ox * dx + oy * dy, C, a_ok)
    # Part of the ray inside the infinite cylinder; a ray parallel to the axis is in it
    # everywhere or nowhere.
    lat_lo = jnp.where(a_ok, jnp.where(ok, _minimum(t1, t2), _INF), jnp.where(C <= 0.0, -_INF, _INF))
    lat_hi = jnp.where(a_ok, jnp.where(ok, _maximum(t1, t2), -_INF), jnp.where(C <= 0.0, _INF, -_INF))
    z_lo, z_hi = _slab(oz, dz, length / 2.0, dd)
    return _interval_hit(_maximum(lat_lo, z_lo), _minimum(lat_hi, z_hi), t_min)


def _ray_cone(o, d, dims, t_min):
    R, L = dims[..., 0], dims[..., 1]
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    dd = _dot(d, d)
    half = L / 2.0
    # Lateral surface: L² (x² + y²) = R² (L/2 - z)², with L/2 - z >= 0 (the lower nappe).
    h0 = half - oz
    L2, R2 = L * L, R * R
    A = L2 * (dx * dx + dy * dy) - R2 * dz * dz
    B = L2 * (ox * dx + oy * dy) + R2 * h0 * dz
    C = L2 * (ox * ox + oy * oy) - R2 * h0 * h0
    a_ok = jnp.abs(A) > _PARALLEL * (L2 + R2) * dd
    t1, t2, ok1, ok2 = _quadratic_roots(A, B, C, a_ok)
    z_tol = _EDGE * (L + R)

    def on_side(t, ok):
        z = oz + t * dz
        return ok & (z >= -half - z_tol) & (z <= half + z_tol)

    # Base disc at z = -L/2.
    base_ok = dz * dz > _PARALLEL * dd
    tb = _safe_div(-half - oz, dz, base_ok)
    xb, yb = ox + tb * dx, oy + tb * dy
    base_ok = base_ok & (xb * xb + yb * yb <= R2 * (1.0 + _EDGE))
    return _first_hit([t1, t2, tb], [on_side(t1, ok1), on_side(t2, ok2), base_ok], t_min)


def _ray_tube(o, d, dims, t_min):
    R, ri, L = dims[..., 0], dims[..., 1], dims[..., 2]
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    dd = _dot(d, d)
    half = L / 2.0
    z_tol = _EDGE * (L + R)
    A = dx * dx + dy * dy
    B = ox * dx + oy * dy
    rho2 = ox * ox + oy * oy
    a_ok = A > _PARALLEL * dd
    ts, oks = [], []
    for radius, exists in ((R, R > 0.0), (ri, ri > 0.0)):  # outer and inner walls (no bore: no wall)
        t1, t2, ok1, ok2 = _quadratic_roots(A, B, rho2 - radius * radius, a_ok)
        for t, ok in ((t1, ok1), (t2, ok2)):
            z = oz + t * dz
            ts.append(t)
            oks.append(ok & a_ok & exists & (jnp.abs(z) <= half + z_tol))
    cap_ok = dz * dz > _PARALLEL * dd
    for zc in (-half, half):  # annular end faces
        t = _safe_div(zc - oz, dz, cap_ok)
        x, y = ox + t * dx, oy + t * dy
        r2 = x * x + y * y
        ts.append(t)
        oks.append(cap_ok & (r2 <= R * R * (1.0 + _EDGE)) & (r2 >= ri * ri * (1.0 - _EDGE)))
    return _first_hit(ts, oks, t_min)


def _ray_rectangle(o, d, dims, t_min, bounded=True):
    dz = d[..., 2]
    ok = dz * dz > _PARALLEL * _dot(d, d)
    t = _safe_div(-o[..., 2], dz, ok)
    if bounded:
        x = o[..., 0] + t * d[..., 0]
        y = o[..., 1] + t * d[..., 1]
        ok = ok & (jnp.abs(x) <= dims[..., 0] / 2.0) & (jnp.abs(y) <= dims[..., 1] / 2.0)
    return _first_hit([t], [ok], t_min)


def _moller_trumbore(o, d, a, b, c):
    """Two-sided Möller–Trumbore: ray parameter and whether the ray meets the triangle (broadcast)."""
    e1, e2 = _tsub(b, a), _tsub(c, a)
    pvec = _tcross(d, e2)
    det = _tdot(e1, pvec)
    ok = det * det > _PARALLEL * _tdot(d, d) * _tdot(e1, e1) * _tdot(e2, e2)
    inv = _safe_div(1.0, det, ok)
    tvec = _tsub(o, a)
    u = _tdot(tvec, pvec) * inv
    qvec = _tcross(tvec, e1)
    v = _tdot(d, qvec) * inv
    t = _tdot(e2, qvec) * inv
    ok = ok & (u >= -_EDGE) & (v >= -_EDGE) & (u + v <= 1.0 + _EDGE)
    return t, ok


def _ray_mesh(o, d, dims, mesh, t_min):
    tri = _mesh_triangles(mesh)  # (f, 3, 3)
    if len(tri) == 0:
        return jnp.full(jnp.broadcast_shapes(o.shape[:-1], d.shape[:-1], dims.shape[:-1]), _INF)
    sg = jax.lax.stop_gradient
    # Every triangle, without derivatives: which one is hit first.
    every = jnp.asarray(tri) * sg(dims)[..., None, None, :]  # (..., f, 3, 3)
    t, ok = _moller_trumbore(_components(sg(o), True), _components(sg(d), True), *_triangle_components(every))
    ok = ok & (t >= t_min)
    first = jnp.argmin(jnp.where(ok, t, _INF), axis=-1)
    hit = jnp.any(ok, axis=-1)
    # That triangle again, differentiably: derivatives cost one triangle per ray, not f.
    chosen = jnp.asarray(tri)[first] * dims[..., None, :]  # (..., 3, 3)
    t, _ = _moller_trumbore(_components(o), _components(d), *_triangle_components(chosen))
    return jnp.where(hit, t, _INF)


def ray_hit(kind: str, origin: Array, direction: Array, dims: Array, mesh=None, t_min: float = 1e-9) -> Array:
    """First intersection of rays with one shape, in the shape's own frame.

    Parameters
    ----------
    kind : str
        The shape kind (one of :data:`RAY_KINDS`); static.
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
    _check_kind(kind, mesh)
    o = _as_float(origin)
    d = _as_float(direction)
    dims = _as_float(dims)
    if kind == "box":
        return _ray_box(o, d, dims, t_min)
    if kind == "sphere":
        return _ray_sphere(o, d, dims, t_min)
    if kind == "cylinder":
        return _ray_cylinder(o, d, dims, t_min)
    if kind == "cone":
        return _ray_cone(o, d, dims, t_min)
    if kind == "tube":
        return _ray_tube(o, d, dims, t_min)
    if kind == "rectangle":
        return _ray_rectangle(o, d, dims, t_min)
    if kind == "plane":
        return _ray_rectangle(o, d, dims, t_min, bounded=False)
    return _ray_mesh(o, d, dims, mesh, t_min)


# ---- distance to a surface ----------------------------------------------------------------------------


def _segment_distance2(px: Array, py: Array, a: tuple[Array, Array], b: tuple[Array, Array]) -> Array:
    """Squared distance from 2-D points (px, py) to the segment a-b."""
    ex, ey = b[0] - a[0], b[1] - a[1]
    wx, wy = px - a[0], py - a[1]
    ee = ex * ex + ey * ey
    s = jnp.clip(_safe_div(wx * ex + wy * ey, ee, ee > 0.0), 0.0, 1.0)
    rx, ry = wx - s * ex, wy - s * ey
    return rx * rx + ry * ry


def _revolved_distance(p: Array, segments, masks=None) -> Array:
    """Distance to a surface of revolution about z whose meridian (rho, z) is a polyline.

    The nearest point of such a surface lies in the point's own meridian half-plane, so the
    3-D distance is the 2-D distance from (rho, z) to the generating segments.
    """
    rho = _safe_sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
    z = p[..., 2]
    d2 = [_segment_distance2(rho, z, a, b) for a, b in segments]
    if masks is not None:
        d2 = [jnp.where(m, x, _INF) for x, m in zip(d2, masks)]
    d2 = jnp.stack(jnp.broadcast_arrays(*d2), axis=-1)
    return _safe_sqrt(_min_last(d2))


def _box_distance(p, dims):
    q = jnp.abs(p) - dims / 2.0
    outside = _safe_sqrt(jnp.sum(jnp.where(q > 0.0, q, 0.0) ** 2, axis=-1))
    deepest = _max_last(q)
    inside = -jnp.where(deepest < 0.0, deepest, 0.0)
    return outside + inside


def _triangle_distance2(p, a, b, c):
    """Squared distance from points to triangles (component tuples, broadcast).

    The closest point is found by the Voronoi-region test on barycentric quantities (vertex,
    edge or face region), evaluated for every region and selected with ``where``.
    """
    ab, ac, bc = _tsub(b, a), _tsub(c, a), _tsub(c, b)
    ap, bp, cp = _tsub(p, a), _tsub(p, b), _tsub(p, c)
    d1, d2 = _tdot(ab, ap), _tdot(ac, ap)
    d3, d4 = _tdot(ab, bp), _tdot(ac, bp)
    d5, d6 = _tdot(ab, cp), _tdot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    in_a = (d1 <= 0.0) & (d2 <= 0.0)
    in_b = (d3 >= 0.0) & (d4 <= d3)
    in_c = (d6 >= 0.0) & (d5 <= d6)
    in_ab = (vc <= 0.0) & (d1 >= 0.0) & (d3 <= 0.0)
    in_ac = (vb <= 0.0) & (d2 >= 0.0) & (d6 <= 0.0)
    in_bc = (va <= 0.0) & (d4 >= d3) & (d5 >= d6)
    e_bc = (d4 - d3) + (d5 - d6)
    den = va + vb + vc
    v = _safe_div(vb, den, den != 0.0)
    w = _safe_div(vc, den, den != 0.0)
    closest = _tlerp(_tlerp(a, v, ab), w, ac)  # face region, lowest priority
    closest = _tselect(in_bc, _tlerp(b, _safe_div(d4 - d3, e_bc, e_bc != 0.0), bc), closest)
    closest = _tselect(in_ac, _tlerp(a, _safe_div(d2, d2 - d6, d2 != d6), ac), closest)
    closest = _tselect(in_c, c, closest)
    closest = _tselect(in_ab, _tlerp(a, _safe_div(d1, d1 - d3, d1 != d3), ab), closest)
    closest = _tselect(in_b, b, closest)
    closest = _tselect(in_a, a, closest)
    r = _tsub(p, closest)
    return _tdot(r, r)


def _mesh_distance(p, dims, mesh):
    tri = _mesh_triangles(mesh)
    if len(tri) == 0:
        return jnp.full(jnp.broadcast_shapes(p.shape[:-1], dims.shape[:-1]), _INF)
    sg = jax.lax.stop_gradient
    # Every triangle, without derivatives: which one is nearest; then that one differentiably.
    every = jnp.asarray(tri) * sg(dims)[..., None, None, :]
    nearest = jnp.argmin(_triangle_distance2(_components(sg(p), True), *_triangle_components(every)), axis=-1)
    chosen = jnp.asarray(tri)[nearest] * dims[..., None, :]
    return _safe_sqrt(_triangle_distance2(_components(p), *_triangle_components(chosen)))


def surface_distance(kind: str, p: Array, dims: Array, mesh=None) -> Array:
    """Unsigned distance from points to the surface of one shape, in the shape's own frame.

    Parameters
    ----------
    kind : str
        The shape kind (one of :data:`RAY_KINDS`); static.
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
    _check_kind(kind, mesh)
    p = _as_float(p)
    dims = _as_float(dims)
    if kind == "box":
        return _box_distance(p, dims)
    if kind == "sphere":
        return jnp.abs(_safe_sqrt(_dot(p, p)) - dims[..., 0])
    if kind == "cylinder":
        r, h = dims[..., 0], dims[..., 1] / 2.0
        zero = jnp.zeros_like(r)
        return _revolved_distance(p, [((zero, -h), (r, -h)), ((r, -h), (r, h)), ((r, h), (zero, h))])
    if kind == "cone":
        r, h = dims[..., 0], dims[..., 1] / 2.0
        zero = jnp.zeros_like(r)
        return _revolved_distance(p, [((zero, -h), (r, -h)), ((r, -h), (zero, h))])
    if kind == "tube":
        ro, ri, h = dims[..., 0], dims[..., 1], dims[..., 2] / 2.0
        segments = [((ri, -h), (ro, -h)), ((ro, -h), (ro, h)), ((ro, h), (ri, h)), ((ri, h), (ri, -h))]
        true = jnp.ones_like(ri, dtype=bool)
        return _revolved_distance(p, segments, masks=[true, true, true, ri > 0.0])  # no bore: a cylinder
    if kind == "rectangle":
        x = p[..., 0] - jnp.clip(p[..., 0], -dims[..., 0] / 2.0, dims[..., 0] / 2.0)
        y = p[..., 1] - jnp.clip(p[..., 1], -dims[..., 1] / 2.0, dims[..., 1] / 2.0)
        return _safe_sqrt(x * x + y * y + p[..., 2] ** 2)
    if kind == "plane":
        return jnp.abs(p[..., 2])
    return _mesh_distance(p, dims, mesh)


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
    shape_poses = _as_float(shape_poses)
    shape_dims = _as_float(shape_dims)
    origins = _as_float(origins)
    directions = _as_float(directions)
    _check_shapes(shape_poses, shape_dims, shapes)
    ts = []
    for i, shape in enumerate(shapes):
        T = shape_poses[..., i, :, :]
        o = _to_local(T, origins)
        d = jnp.sum(directions[..., :, :, None] * T[..., None, :3, :3], axis=-2)
        ts.append(ray_hit(shape.kind, o, d, shape_dims[..., i, None, :], shape.mesh, t_min))
    if not ts:
        shape = jnp.broadcast_shapes(origins.shape[:-1], directions.shape[:-1], shape_poses.shape[:-3] + (1,))
        return jnp.full(shape, _INF)
    return _min_last(jnp.stack(jnp.broadcast_arrays(*ts), axis=-1))


def distance_to_shapes(shape_poses: Array, shape_dims: Array, shapes: Sequence, points: Array) -> Array:
    """Unsigned distance from world points to the nearest surface of a set of shapes.

    Parameters
    ----------
    shape_poses : (..., S, 4, 4) float
        ``T_world_shape`` of each shape (rigid transforms).
    shape_dims : (..., S, 3) float
        Dimensions of each shape.
    shapes : sequence of ShapeInfo
        The S shapes' static descriptions (anything with ``kind`` and ``mesh`` attributes).
    points : (..., n, 3) float
        World points; leading axes broadcast with those of ``shape_poses``.

    Returns
    -------
    distance : (..., n) float
        Distance to the nearest shape surface (see :func:`surface_distance`); ``inf`` when
        there are no shapes.
    """
    shape_poses = _as_float(shape_poses)
    shape_dims = _as_float(shape_dims)
    points = _as_float(points)
    _check_shapes(shape_poses, shape_dims, shapes)
    ds = []
    for i, shape in enumerate(shapes):
        p = _to_local(shape_poses[..., i, :, :], points)
        ds.append(surface_distance(shape.kind, p, shape_dims[..., i, None, :], shape.mesh))
    if not ds:
        return jnp.full(jnp.broadcast_shapes(points.shape[:-1], shape_poses.shape[:-3] + (1,)), _INF)
    return _min_last(jnp.stack(jnp.broadcast_arrays(*ds), axis=-1))


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
