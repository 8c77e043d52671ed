"""A new shape kind is one registry entry: the checker, ray casting, distances, scene export,
rendering's wireframes and observability all pick it up (docs/architecture.md shows the same
example)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mbcal
from mbcal._jax import jnp
from mbcal.errors import DimensionError, UndefinedNameError, UnitError
from mbcal.geometry import kernels
from mbcal.geometry.raycast import ray_hit, surface_distance
from mbcal.geometry.shapes import ShapeKind, get_shape, register_shape, shape_kinds, unregister_shape


def _disk_ray(o, d, dims, t_min, _mesh=None):
    """A flat disk of radius r in the plane z = 0: where the ray crosses z = 0, inside r."""
    r = dims[..., 0]
    ok = jnp.abs(d[..., 2]) > 1e-12
    t = kernels._safe_div(-o[..., 2], d[..., 2], ok)
    x = o[..., 0] + t * d[..., 0]
    y = o[..., 1] + t * d[..., 1]
    hit = ok & (t >= t_min) & (x * x + y * y <= r * r)
    return jnp.where(hit, t, jnp.inf)


def _disk_distance(p, dims, _mesh=None):
    rho = kernels._safe_sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
    outside = jnp.maximum(rho - dims[..., 0], 0.0)
    return kernels._safe_sqrt(outside**2 + p[..., 2] ** 2)


def _disk_mesh(dims, _mesh, sections, _plane):
    a = np.linspace(0.0, 2 * math.pi, sections, endpoint=False)
    rim = np.stack([dims[0] * np.cos(a), dims[0] * np.sin(a), np.zeros_like(a)], axis=1)
    vertices = np.vstack([np.zeros((1, 3)), rim])
    faces = np.array([[0, 1 + i, 1 + (i + 1) % sections] for i in range(sections)])
    return vertices, faces


DISK = ShapeKind("disk", ("radius",), _disk_ray, _disk_distance, _disk_mesh, flat=True, doc="a flat disk in z = 0")

MODEL = """
param wall.z = 2 m in [1.5 m, 2.5 m]
param disk.radius = 0.5 m
object wall at (0, 0, wall.z) {
  shape face = disk(disk.radius)
}
range sonar(direction = (0, 0, 1), max = 5 m)
range scanner(directions = [(0.1, 0, 1), (0, 0.1, 1), (0.05, 0.05, 1)])
measure range
"""


@pytest.fixture
def disk():
    register_shape(DISK)
    yield DISK
    unregister_shape("disk")


def test_a_registered_toy_shape_works_in_models_ray_casting_and_export(disk):
    model = mbcal.load_model_text(MODEL)
    assert [s.kind for s in model.shapes] == ["disk"]
    assert "1 disk" in model.summary()
    scene = mbcal.modeler(model, model.nominal)
    # Ray casting and distances go through the registry.
    t = ray_hit("disk", jnp.array([0.1, 0.0, -1.0]), jnp.array([0.0, 0.0, 1.0]), jnp.array([0.5, 0.0, 0.0]))
    assert float(t) == pytest.approx(1.0)
    d = surface_distance("disk", jnp.array([0.8, 0.0, 0.4]), jnp.array([0.5, 0.0, 0.0]))
    assert float(d) == pytest.approx(0.5)
    # Scene export builds its mesh (one-sided disk, doubled for a flat shape).
    tm = scene.to_trimesh()
    mesh = tm.to_mesh()
    assert mesh.vertices[:, 2].max() == pytest.approx(2.0)
    assert len(mesh.faces) == 2 * 48
    # A range measurement of the wall's height, simulated and estimated back.
    plan = mbcal.measurements_from_records(
        [{"kind": "range", "sensor": "scanner", "ray": k, "sigma": 0.001} for k in range(3)]
        + [{"kind": "range", "sensor": "sonar", "ray": 0, "sigma": 0.001}],
        model,
    )
    data = mbcal.simulate(model, plan, {"wall.z": 2.1}, noise=0.0)
    assert data.measurements[-1].value[0] == pytest.approx(2.1)
    result = mbcal.calibrate(model, data, ["wall.z"], restarts=4)
    assert result.values["wall.z"] == pytest.approx(2.1, abs=1e-9)


def test_the_checker_types_and_validates_a_registered_shape(disk):
    with pytest.raises(UnitError):
        mbcal.load_model_text("object a { shape s = disk(30 deg) }")
    with pytest.raises(DimensionError, match="radius"):
        mbcal.load_model_text("param r = -1 cm\nobject a { shape s = disk(r) }")


def test_an_unregistered_shape_is_a_located_error_listing_the_kinds():
    assert "disk" not in shape_kinds()
    with pytest.raises(UndefinedNameError, match="unknown shape 'disk'") as err:
        mbcal.load_model_text("object a {\n  shape s = disk(1 m)\n}")
    assert err.value.span.line == 2
    assert "box" in str(err.value)


def test_registering_a_kind_twice_is_refused_unless_replaced(disk):
    with pytest.raises(ValueError, match="already registered"):
        register_shape(DISK)
    assert register_shape(DISK, replace=True) is DISK
    assert get_shape("disk") is DISK
    with pytest.raises(ValueError, match="at most 3"):
        ShapeKind("blob", ("a", "b", "c", "d"), _disk_ray, _disk_distance, _disk_mesh)
