"""Differentiable ray-hit and surface-distance kernels, one per primitive shape.

Each primitive is centred on its own frame's origin with its axis along z; ``dims`` is the
shape's length-3, zero-padded dimension vector (see :mod:`mbcal.geometry.shapes`, which
registers these kernels under the shape kinds, and :mod:`mbcal.geometry.raycast`, which casts
rays against whole scenes).  Everything is JAX (float64), works under ``jit`` and ``vmap``, and
has finite derivatives everywhere: every square root, norm and division that can meet zero is
guarded with the "double where" pattern (the unsafe input is replaced before the operation, the
result is selected after it), so rays that miss, rays parallel to a face and points on an axis
give derivative 0 rather than NaN.

A ray kernel ``ray_KIND(o, d, dims, t_min)`` returns the smallest ``t >= t_min`` with
``o + t d`` on the surface (``inf`` for a miss); a distance kernel ``KIND_distance(p, dims)``
returns the unsigned distance to the surface.  Meshes take their triangles as an extra argument.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from mbcal._jax import jax, jnp

Array = Any

# A component of a direction smaller than this fraction of its length (squared: 1e-24) counts
# as zero: the ray is parallel to the face or axis it belongs to.  This keeps 1/d finite.
_PARALLEL = 1e-24
# Relative slack of the boundary tests where two surfaces of one shape meet (rims, mesh
# edges), so that rays through a seam are not lost between the two.
_EDGE = 1e-12
INF = float("inf")


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


def min_last(x: Array) -> Array:
    i = jnp.argmin(x, axis=-1)
    return jnp.take_along_axis(x, i[..., None], axis=-1)[..., 0]


def _max_last(x: Array) -> Array:
    i = jnp.argmax(x, axis=-1)
    return jnp.take_along_axis(x, i[..., None], axis=-1)[..., 0]


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def as_float(x: Array) -> Array:
    return jnp.asarray(x, dtype=jnp.float64)


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
    return min_last(jnp.where(ok, t, INF))


def _slab(o: Array, d: Array, half: Array, dd: Array):
    """Entry and exit parameters (lo, hi) of a ray in the slab |coordinate| <= half.

    A ray parallel to the slab is inside it for every t (lo = -inf, hi = inf) or never
    (lo = inf, hi = -inf).
    """
    par = d * d <= _PARALLEL * dd
    t1 = _safe_div(-half - o, d, ~par)
    t2 = _safe_div(half - o, d, ~par)
    inside = jnp.abs(o) <= half
    lo = jnp.where(par, jnp.where(inside, -INF, INF), _minimum(t1, t2))
    hi = jnp.where(par, jnp.where(inside, INF, -INF), _maximum(t1, t2))
    return lo, hi


def _interval_hit(near: Array, far: Array, t_min: float) -> Array:
    """First boundary crossing of a ray whose part inside a convex solid is [near, far]."""
    t = jnp.where(near >= t_min, near, far)
    ok = (near <= far) & (t >= t_min) & (t < INF)
    return jnp.where(ok, t, INF)


# ---- ray casting: one kind each ---------------------------------------------------------------------


def ray_box(o, d, dims, t_min):
    dd = _dot(d, d)[..., None]
    lo, hi = _slab(o, d, dims / 2.0, dd)
    return _interval_hit(_max_last(lo), min_last(hi), t_min)


def ray_sphere(o, d, dims, t_min):
    r = dims[..., 0]
    A = _dot(d, d)
    t1, t2, ok1, ok2 = _quadratic_roots(A, _dot(o, d), _dot(o, o) - r * r, A > 0.0)
    return _first_hit([t1, t2], [ok1, ok2], t_min)


def ray_cylinder(o, d, dims, t_min):
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
    lat_lo = jnp.where(a_ok, jnp.where(ok, _minimum(t1, t2), INF), jnp.where(C <= 0.0, -INF, INF))
    lat_hi = jnp.where(a_ok, jnp.where(ok, _maximum(t1, t2), -INF), jnp.where(C <= 0.0, INF, -INF))
    z_lo, z_hi = _slab(oz, dz, length / 2.0, dd)
    return _interval_hit(_maximum(lat_lo, z_lo), _minimum(lat_hi, z_hi), t_min)


def ray_cone(o, d, dims, t_min):
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


def ray_tube(o, d, dims, t_min):
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


def ray_rectangle(o, d, dims, t_min, bounded=True):
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


def ray_mesh(o, d, dims, mesh, t_min):
    tri = _mesh_triangles(mesh)  # (f, 3, 3)
    if len(tri) == 0:
        return jnp.full(jnp.broadcast_shapes(o.shape[:-1], d.shape[:-1], dims.shape[:-1]), INF)
    sg = jax.lax.stop_gradient
    # Every triangle, without derivatives: which one is hit first.
    every = jnp.asarray(tri) * sg(dims)[..., None, None, :]  # (..., f, 3, 3)
    t, ok = _moller_trumbore(_components(sg(o), True), _components(sg(d), True), *_triangle_components(every))
    ok = ok & (t >= t_min)
    first = jnp.argmin(jnp.where(ok, t, INF), axis=-1)
    hit = jnp.any(ok, axis=-1)
    # That triangle again, differentiably: derivatives cost one triangle per ray, not f.
    chosen = jnp.asarray(tri)[first] * dims[..., None, :]  # (..., 3, 3)
    t, _ = _moller_trumbore(_components(o), _components(d), *_triangle_components(chosen))
    return jnp.where(hit, t, INF)


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
        d2 = [jnp.where(m, x, INF) for x, m in zip(d2, masks)]
    stacked = jnp.stack(jnp.broadcast_arrays(*d2), axis=-1)
    return _safe_sqrt(min_last(stacked))


def box_distance(p, dims):
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


def mesh_distance(p, dims, mesh):
    tri = _mesh_triangles(mesh)
    if len(tri) == 0:
        return jnp.full(jnp.broadcast_shapes(p.shape[:-1], dims.shape[:-1]), INF)
    sg = jax.lax.stop_gradient
    # Every triangle, without derivatives: which one is nearest; then that one differentiably.
    every = jnp.asarray(tri) * sg(dims)[..., None, None, :]
    nearest = jnp.argmin(_triangle_distance2(_components(sg(p), True), *_triangle_components(every)), axis=-1)
    chosen = jnp.asarray(tri)[nearest] * dims[..., None, :]
    return _safe_sqrt(_triangle_distance2(_components(p), *_triangle_components(chosen)))


def sphere_distance(p, dims):
    return jnp.abs(_safe_sqrt(_dot(p, p)) - dims[..., 0])


def cylinder_distance(p, dims):
    r, h = dims[..., 0], dims[..., 1] / 2.0
    zero = jnp.zeros_like(r)
    return _revolved_distance(p, [((zero, -h), (r, -h)), ((r, -h), (r, h)), ((r, h), (zero, h))])


def cone_distance(p, dims):
    r, h = dims[..., 0], dims[..., 1] / 2.0
    zero = jnp.zeros_like(r)
    return _revolved_distance(p, [((zero, -h), (r, -h)), ((r, -h), (zero, h))])


def tube_distance(p, dims):
    ro, ri, h = dims[..., 0], dims[..., 1], dims[..., 2] / 2.0
    segments = [((ri, -h), (ro, -h)), ((ro, -h), (ro, h)), ((ro, h), (ri, h)), ((ri, h), (ri, -h))]
    true = jnp.ones_like(ri, dtype=bool)
    return _revolved_distance(p, segments, masks=[true, true, true, ri > 0.0])  # no bore: a cylinder


def rectangle_distance(p, dims):
    x = p[..., 0] - jnp.clip(p[..., 0], -dims[..., 0] / 2.0, dims[..., 0] / 2.0)
    y = p[..., 1] - jnp.clip(p[..., 1], -dims[..., 1] / 2.0, dims[..., 1] / 2.0)
    return _safe_sqrt(x * x + y * y + p[..., 2] ** 2)


def plane_distance(p, dims):
    return jnp.abs(p[..., 2])
