"""Headless rendering agrees with the model: pixels with projections, depth with range rays."""

from __future__ import annotations

import numpy as np
import pytest

from mbcal.language import load_model, load_model_text
from mbcal.modeling import modeler
from mbcal.render.views import render_view, wireframe_layer

from conftest import MODELS

pytestmark = pytest.mark.render


def test_rendered_point_lies_within_one_pixel_of_its_projection():
    model = load_model(MODELS / "teleexistence.mdl")
    scene = modeler(model, model.nominal)
    view = render_view(scene, "eyes.left", points=True, point_radius=0.003)
    cam = scene.camera("eyes.left")
    projected = np.asarray(cam.project(scene.points))
    depth = np.asarray(cam.to_camera(scene.points))[:, 2]
    fx = float(cam.intrinsics[0])
    checked = 0
    for k, p in enumerate(model.points):
        mask = view.shape_index == len(model.shapes) + k
        whole_disc = np.pi * (fx * 0.003 / depth[k]) ** 2
        if mask.sum() < 0.85 * whole_disc:
            continue  # partly hidden (the lever's tip sits on its knob): its centroid is not its centre
        rows, cols = np.nonzero(mask)
        centroid = np.array([cols.mean(), rows.mean()])
        assert np.linalg.norm(centroid - projected[k]) < 1.0, p.name
        checked += 1
    assert checked >= 8  # points on free surfaces; corners and pipe ends are half inside their solid


@pytest.mark.slow
def test_rendered_depth_matches_the_range_measurement_model():
    # A camera and a range sensor at the same pose, the sensor's rays through chosen pixels.
    pixels = [(50, 40), (320, 240), (600, 420), (100, 400), (520, 90)]
    fx, fy, cx, cy = 500.0, 520.0, 319.5, 239.5
    directions = ", ".join(f"(({u} - {cx}) / {fx}, ({v} - {cy}) / {fy}, 1)" for u, v in pixels)
    text = f"""
    param room.yaw = 8 deg
    frame room at rot_z(room.yaw) {{
      shape wall = rectangle(6 m, 4 m) at (0, 3 m, 1 m) * rot_x(90 deg)
      shape crate = box(60 cm, 40 cm, 50 cm) at (0.3 m, 1.8 m, 0.9 m) * rot_z(20 deg)
      shape drum = cylinder(25 cm, 80 cm) at (-0.6 m, 2.2 m, 0.7 m)
      shape ball = sphere(20 cm) at (0.5 m, 1.5 m, 1.6 m)
    }}
    frame eye at look_at(eye = (0, 0, 1.2 m), target = (0, 2 m, 1.1 m)) {{
      camera cam(width = 640, height = 480, fx = {fx}, fy = {fy}, cx = {cx}, cy = {cy})
      range probe(directions = [{directions}])
    }}
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    view = render_view(scene, "cam")
    from mbcal.geometry.raycast import scene_cast_rays

    origins, dirs = scene.range_rays("probe")
    ranges = np.asarray(scene_cast_rays(scene, origins, dirs))
    for (u, v), r in zip(pixels, ranges):
        z = view.depth[v, u]
        norm = np.linalg.norm([(u - cx) / fx, (v - cy) / fy, 1.0])
        assert z > 0
        assert abs(z * norm - r) < 1e-3, (u, v, z * norm, r)


def test_hidden_edges_are_not_drawn():
    # A small box hidden behind a big one: none of its edges may be visible.
    text = """
    camera cam(width = 320, height = 240, f = 300) at look_at(eye = (0, 0, 0), target = (0, 2 m, 0))
    object front at (0, 2 m, 0) { shape box(1 m, 0.2 m, 1 m) }
    object behind at (0, 3 m, 0) { shape box(0.3 m, 0.3 m, 0.3 m) }
    object aside at (1.2 m, 3 m, 0) { shape box(0.3 m, 0.3 m, 0.3 m) }
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    view = render_view(scene, "cam")
    layer = wireframe_layer(scene, "cam", view, (255, 0, 0))
    from mbcal.render.views import wireframe_segments

    segments = wireframe_segments(scene, "cam")
    behind = np.all(np.abs(segments[:, :, 1] - 3.0) <= 0.15 + 1e-9, axis=1) & np.all(
        np.abs(segments[:, :, 0]) < 0.2, axis=1
    )
    aside = np.all(segments[:, :, 0] > 1.0, axis=1)
    visible = np.array([vis.any() for _, vis in layer.data])
    assert behind.any() and aside.any()
    assert not visible[behind].any()
    assert visible[aside].any()


def test_a_model_without_shapes_renders_its_points_on_the_background():
    """It raised 'NumPy boolean array indexing assignment cannot assign 3 input values to the 0
    output values' (mbcal render, and --overlay after a whole solve)."""
    model = load_model_text(
        "param a = 0 m\nframe f at (a, 0, 1 m) {\n  point p = (0, 0, 0)\n}\n"
        "camera eye(width = 64, height = 48, f = 50) at look_at(eye = (0, -3 m, 1 m), target = (0, 0, 1 m))\n"
    )
    view = render_view(modeler(model, model.nominal), "eye", points=True, point_radius=0.05)
    assert view.color.shape == (48, 64, 3)
    assert np.any(view.shape_index == 0) and (view.shape_index[24, 32] == 0)  # the point, at the centre


def test_a_renderer_that_fails_is_a_render_error_naming_the_camera(monkeypatch):
    """A driver's refusal (a camera larger than OpenGL's renderbuffers) ended mbcal render in a
    traceback and exit status 1, the status of an untrustworthy fit."""
    import pyrender

    from mbcal.errors import RenderError

    model = load_model_text("camera eye(width = 64, height = 48, f = 50)\nshape box(1 m, 1 m, 1 m) at (0, 0, 3 m)\n")
    scene = modeler(model, model.nominal)

    def refuse(self, *args, **kwargs):
        raise RuntimeError("GLError(\n\terr = 1281,\n\tdescription = b'invalid value'\n)")

    with monkeypatch.context() as patch:
        patch.setattr(pyrender.OffscreenRenderer, "render", refuse)
        with pytest.raises(RenderError) as info:
            render_view(scene, "eye")
    assert str(info.value).startswith(
        "cannot render camera 'eye' (64×48 px): RuntimeError: GLError( err = 1281, description = b'invalid value' )"
    )
    assert render_view(scene, "eye").color.shape == (48, 64, 3)  # the failed context was closed
