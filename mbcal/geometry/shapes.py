"""The shape registry: every shape kind the language knows, in one table.

A :class:`ShapeKind` says everything mbcal needs to know about one kind of shape:

* its dimension arguments (names, in order, at most three) and their physical dimension — the
  checker types ``shape box(40 cm, 30 cm, 40 cm)`` from them;
* which dimension values are valid (positive; a tube's bore smaller than the tube) — the checker
  tests them at the nominal parameter values;
* a differentiable ray-hit kernel and a surface-distance kernel (JAX) — range sensors and
  point-to-surface measurements use them through :mod:`mbcal.geometry.raycast`;
* a triangle mesh builder (trimesh) — scene export and the renderer draw it;
* how a URDF ``<geometry>`` element maps to it.

The built-in kinds are registered below; a new kind is one :func:`register_shape` call (see
docs/architecture.md for a worked example).  Every primitive is centred on its own frame's origin
with its axis along z; the modeler packs the dimensions into a zero-padded length-3 vector:

==========  ===========================  ================================================
kind        dims                         surface
==========  ===========================  ================================================
box         (sx, sy, sz)                 full side lengths
cylinder    (radius, length)             solid closed cylinder, z in [-length/2, length/2]
cone        (radius, length)             base disc at z = -length/2, apex at +length/2
sphere      (radius)                     the sphere
tube        (outer, inner, length)       outer and inner walls, two annular end faces
rectangle   (sx, sy)                     |x| <= sx/2, |y| <= sy/2 in the plane z = 0
plane       ()                           the infinite plane z = 0 (``plane(sx, sy)``: a rectangle)
mesh        (scale_x, scale_y, scale_z)  a mesh file's triangles, vertices scaled per axis
==========  ===========================  ================================================
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbcal.units import DIMENSIONLESS, LENGTH, Dim

__all__ = [
    "ShapeKind",
    "register_shape",
    "unregister_shape",
    "get_shape",
    "shape_kinds",
    "shape_mesh",
    "runtime_shapes",
    "BUILTIN_SHAPES",
    "MAX_DIMS",
]

Array = Any
MAX_DIMS = 3  # the modeler packs a shape's dimensions into a length-3 vector


def _positive(kind: ShapeKind, values: Sequence[float]) -> tuple[int, str] | None:
    """The default rule: every dimension is positive."""
    unit = " m" if kind.dim == LENGTH else ""
    for i, (name, v) in enumerate(zip(kind.dims, values)):
        if not (np.isfinite(v) and v > 0):
            return i, f"{kind.name}() dimension '{name}' must be positive, got {v:g}{unit} at the nominal values"
    return None


@dataclass(frozen=True)
class ShapeKind:
    """One kind of shape: its arguments, its validity rule, its kernels and its mesh.

    Attributes
    ----------
    name : str
        The kind's name in the language (``shape NAME(...)``).
    dims : tuple of str
        Names of the dimension arguments, in order (at most three).
    ray : callable
        ``ray(origin (..., 3), direction (..., 3), dims (..., 3), t_min, mesh) -> t (...)``: the
        first hit at or beyond ``t_min`` in the shape's frame, ``inf`` for a miss; JAX,
        differentiable, finite derivatives everywhere.
    distance : callable
        ``distance(points (..., 3), dims (..., 3), mesh) -> (...)``: unsigned distance to the
        surface in the shape's frame; JAX, differentiable.
    mesh : callable
        ``mesh(dims (3,) numpy, mesh_data, sections, plane_size) -> (vertices (v, 3), faces (f, 3))``:
        a triangle mesh of the surface in the shape's frame (one-sided: flat kinds get their back
        faces from :meth:`trimesh`).
    dim : Dim
        The physical dimension of every dimension argument (a length for all built-ins).
    flat : bool
        A surface without volume (drawn from both sides, outlined by its border in wireframes).
    bounded : bool
        False for an infinite surface (drawn as a large square, no edges in wireframes).
    validate : callable, optional
        ``validate(kind, values) -> (index, message) | None``: what makes dimension values invalid,
        checked by the model checker at the nominal values.  Default: every dimension must be
        positive.
    sized : str, optional
        The kind this one becomes when it is given dimensions (``plane(1 m, 2 m)`` is a rectangle).
    from_file : bool
        The shape is read from a file (``mesh("part.stl", scale = ...)``): its kernels need the
        triangles, and the checker reads the file instead of typing dimension arguments.
    urdf : (str, tuple of str), optional
        The URDF ``<geometry>`` child this kind stands for and its attributes, in the order of
        ``dims`` (``("cylinder", ("radius", "length"))``; ``box``'s one ``size`` attribute holds
        three numbers).
    doc : str
        One line for documentation and error messages.
    """

    name: str
    dims: tuple[str, ...]
    ray: Callable[..., Array]
    distance: Callable[..., Array]
    mesh: Callable[..., tuple[np.ndarray, np.ndarray]]
    dim: Dim = LENGTH
    flat: bool = False
    bounded: bool = True
    validate: Callable[[ShapeKind, Sequence[float]], tuple[int, str] | None] | None = field(default=None, repr=False)
    sized: str | None = None
    from_file: bool = False
    urdf: tuple[str, tuple[str, ...]] | None = None
    doc: str = ""

    def __post_init__(self) -> None:
        if not self.name.isidentifier():
            raise ValueError(f"a shape kind's name must be an identifier, got '{self.name}'")
        if len(self.dims) > MAX_DIMS:
            raise ValueError(f"shape kind '{self.name}' has {len(self.dims)} dimensions; at most {MAX_DIMS}")

    def invalid(self, values: Sequence[float]) -> tuple[int, str] | None:
        """Why dimension values (SI) are invalid: (index of the culprit, message), or None."""
        rule = self.validate or _positive
        return rule(self, [float(v) for v in values])

    def require_mesh(self, mesh: object) -> None:
        """Refuse to cast against a file shape without its triangles."""
        if self.from_file and mesh is None:
            raise ValueError(f"a '{self.name}' shape needs its MeshData (vertices and faces)")

    def trimesh(
        self,
        dims: np.ndarray,
        mesh_data: object = None,
        *,
        plane_size: float = 10.0,
        sections: int = 48,
        two_sided: bool = True,
    ):
        """A :class:`trimesh.Trimesh` of the shape in its own frame.

        Flat kinds get faces on both sides unless ``two_sided`` is False (renderers that draw
        back faces themselves, where doubled faces would fight for the depth buffer).
        """
        import trimesh  # loaded when a mesh is first drawn or exported: keeps start-up light

        vertices, faces = self.mesh(np.asarray(dims, dtype=float), mesh_data, sections, plane_size)
        if self.flat and two_sided:
            faces = np.concatenate([faces, faces[:, ::-1]])
        return trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64), process=False)


_REGISTRY: dict[str, ShapeKind] = {}


def register_shape(kind: ShapeKind, *, replace: bool = False) -> ShapeKind:
    """Add a shape kind to the language (and to ray casting, export, rendering and the checker).

    Raises
    ------
    ValueError
        A kind of that name exists and ``replace`` is False.
    """
    if kind.name in _REGISTRY and not replace:
        raise ValueError(f"shape kind '{kind.name}' is already registered (pass replace=True to replace it)")
    _REGISTRY[kind.name] = kind
    return kind


def unregister_shape(name: str) -> None:
    """Remove a shape kind (tests that register a toy kind clean up with this)."""
    _REGISTRY.pop(name, None)


def shape_kinds() -> dict[str, ShapeKind]:
    """Every registered shape kind by name, built-ins first."""
    return dict(_REGISTRY)


def get_shape(name: str) -> ShapeKind:
    """The registered kind called ``name``.

    Raises
    ------
    ValueError
        No such kind; the message lists the registered ones.  (A model that names an unknown
        kind gets a located error from the checker instead.)
    """
    found = _REGISTRY.get(name)
    if found is None:
        raise ValueError(f"unknown shape kind '{name}' (expected one of {', '.join(_REGISTRY)})")
    return found


def shape_mesh(
    kind: str,
    dims: np.ndarray,
    mesh_data: object = None,
    *,
    plane_size: float = 10.0,
    sections: int = 48,
    two_sided: bool = True,
):
    """A :class:`trimesh.Trimesh` of one shape of kind ``kind`` in its own frame (see :meth:`ShapeKind.trimesh`)."""
    return get_shape(kind).trimesh(dims, mesh_data, plane_size=plane_size, sections=sections, two_sided=two_sided)


# ---- mesh builders of the built-in kinds --------------------------------------------------------------
# Each returns (vertices, faces) in the shape's frame; trimesh's creation helpers are loaded lazily.


def _creation():
    import trimesh.creation  # see ShapeKind.trimesh

    return trimesh.creation


def _arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _box_mesh(dims, _mesh, _sections, _plane):
    return _arrays(_creation().box(extents=dims[:3]))


def _cylinder_mesh(dims, _mesh, sections, _plane):
    return _arrays(_creation().cylinder(radius=dims[0], height=dims[1], sections=sections))


def _cone_mesh(dims, _mesh, sections, _plane):
    cone = _creation().cone(radius=dims[0], height=dims[1], sections=sections)
    cone.apply_translation([0.0, 0.0, -dims[1] / 2.0])
    return _arrays(cone)


def _sphere_mesh(dims, _mesh, _sections, _plane):
    return _arrays(_creation().icosphere(subdivisions=3, radius=dims[0]))


def _tube_mesh(dims, _mesh, sections, _plane):
    return _arrays(_creation().annulus(r_min=dims[1], r_max=dims[0], height=dims[2], sections=sections))


def _quad(sx: float, sy: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-sx / 2, -sy / 2, 0], [sx / 2, -sy / 2, 0], [sx / 2, sy / 2, 0], [-sx / 2, sy / 2, 0]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _rectangle_mesh(dims, _mesh, _sections, _plane):
    return _quad(dims[0], dims[1])


def _plane_mesh(_dims, _mesh, _sections, plane_size):
    return _quad(plane_size, plane_size)


def _file_mesh(dims, mesh, _sections, _plane):
    return np.asarray(mesh.vertices, dtype=float) * dims[:3], np.asarray(mesh.faces)


def _tube_valid(kind: ShapeKind, values: Sequence[float]) -> tuple[int, str] | None:
    bad = _positive(kind, values)
    if bad is None and not values[1] < values[0]:
        return 1, f"a tube's inner radius ({values[1]:g} m) must be smaller than its outer radius ({values[0]:g} m)"
    return bad


def _scales_valid(_kind: ShapeKind, values: Sequence[float]) -> tuple[int, str] | None:
    for i, v in enumerate(values):
        if not (np.isfinite(v) and v > 0):
            return i, f"a mesh scale must be positive, got {v:g}"
    return None


def _kernels():
    from mbcal.geometry import kernels  # lazy: the kernels need JAX, and 'mbcal check' must not load it

    return kernels


def _primitive(ray: str, **options: Any) -> Callable[..., Array]:
    """A primitive's ray kernel (by name) in the registry's signature (the mesh argument is unused)."""
    return lambda o, d, dims, t_min, _mesh=None: getattr(_kernels(), ray)(o, d, dims, t_min, **options)


def _surface(distance: str) -> Callable[..., Array]:
    return lambda p, dims, _mesh=None: getattr(_kernels(), distance)(p, dims)


def _mesh_ray(o, d, dims, t_min, mesh):
    return _kernels().ray_mesh(o, d, dims, mesh, t_min)


def _mesh_surface(p, dims, mesh):
    return _kernels().mesh_distance(p, dims, mesh)


for _kind in (
    ShapeKind("box", ("sx", "sy", "sz"), _primitive("ray_box"), _surface("box_distance"), _box_mesh,
              urdf=("box", ("size",)), doc="a box with full side lengths sx, sy, sz"),
    ShapeKind("cylinder", ("radius", "length"), _primitive("ray_cylinder"), _surface("cylinder_distance"),
              _cylinder_mesh, urdf=("cylinder", ("radius", "length")), doc="a closed cylinder along z"),
    ShapeKind("cone", ("radius", "length"), _primitive("ray_cone"), _surface("cone_distance"), _cone_mesh,
              doc="a cone along z, base at -length/2"),
    ShapeKind("sphere", ("radius",), _primitive("ray_sphere"), _surface("sphere_distance"), _sphere_mesh,
              urdf=("sphere", ("radius",)), doc="a sphere"),
    ShapeKind("tube", ("outer", "inner", "length"), _primitive("ray_tube"), _surface("tube_distance"), _tube_mesh,
              validate=_tube_valid, doc="a pipe along z: outer and inner radius, length"),
    ShapeKind("rectangle", ("sx", "sy"), _primitive("ray_rectangle"), _surface("rectangle_distance"),
              _rectangle_mesh, flat=True, doc="a rectangle in the plane z = 0"),
    ShapeKind("plane", (), _primitive("ray_rectangle", bounded=False), _surface("plane_distance"), _plane_mesh,
              flat=True, bounded=False, sized="rectangle", doc="the infinite plane z = 0"),
    ShapeKind("mesh", ("sx", "sy", "sz"), _mesh_ray, _mesh_surface, _file_mesh, dim=DIMENSIONLESS,
              validate=_scales_valid, from_file=True, doc="a mesh file's triangles, scaled per axis"),
):  # fmt: skip
    register_shape(_kind)
_BUILTINS = dict(_REGISTRY)
del _kind

BUILTIN_SHAPES = frozenset(_REGISTRY)
"""The kinds mbcal ships; any other was registered at run time (see :func:`runtime_shapes`)."""


def runtime_shapes() -> list[ShapeKind]:
    """Kinds registered at run time (not shipped with mbcal).  Their code is not part of mbcal's
    source fingerprint, so compiled programs that use them are not cached across processes."""
    return [kind for name, kind in _REGISTRY.items() if name not in BUILTIN_SHAPES or kind is not _BUILTINS[name]]
