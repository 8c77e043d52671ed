"""The model language: every construct parses, checks and means what the reference says."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mbcal import errors
from mbcal.language import load_model, load_model_text
from mbcal.language.parse import grammar_path, parse_text
from mbcal.modeling import modeler

from conftest import MODELS


@pytest.mark.parametrize("path", sorted(MODELS.glob("*.mdl")), ids=lambda p: p.name)
def test_every_bundled_model_parses_and_builds(path):
    model = load_model(path)
    scene = modeler(model, model.nominal)
    assert np.all(np.isfinite(np.asarray(scene.points)))
    assert np.all(np.isfinite(np.asarray(scene.frame_poses)))


def test_teleexistence_model_has_the_seeds_objects_and_a_669x453_stereo_camera():
    model = load_model(MODELS / "teleexistence.mdl")
    assert {"room.x", "room.y", "room.z", "room.roll", "room.pitch", "room.yaw", "lever.angle"} <= set(
        model.names("param")
    )
    assert [(c.width, c.height) for c in model.cameras] == [(669, 453), (669, 453)]
    kinds = {s.kind for s in model.shapes}
    assert {"tube", "box", "cylinder", "sphere", "cone"} <= kinds
    assert len(model.points) >= 24
    # The lever is about 0.8 m from the cameras, as in section 4.2.
    scene = modeler(model, model.nominal)
    left = np.asarray(scene.camera("eyes.left").center)
    hub = np.asarray(scene.point("lever.hub"))
    assert 0.7 < np.linalg.norm(hub - left) < 0.9


def test_arm_model_has_seven_offsets_torso_and_three_dof_neck():
    model = load_model(MODELS / "arm7.mdl")
    offsets = model.match_params("arm.offset*")
    assert offsets == [f"arm.offset{i}" for i in range(1, 8)]
    assert all(model.param(f"arm.q{i}").per_configuration for i in range(1, 8))
    assert model.param("torso.q").per_configuration
    assert [f.joint is not None for f in model.frames].count(True) == 1 + 3 + 7


def test_units_are_normalised_to_metres_and_radians():
    model = load_model_text(
        "param a = 25 mm\nparam b = 3 cm\nparam c = 90 deg\nparam d = 2 inch\nparam e = 0.5\n"
        "param f = 1 km\nparam g = 5 mrad\n"
    )
    values = dict(zip(model.names("param"), model.nominal))
    assert values["a"] == pytest.approx(0.025)
    assert values["b"] == pytest.approx(0.03)
    assert values["c"] == pytest.approx(math.pi / 2)
    assert values["d"] == pytest.approx(0.0508)
    assert values["e"] == 0.5
    assert values["f"] == pytest.approx(1000.0)
    assert values["g"] == pytest.approx(0.005)


def test_parameter_range_sigma_and_per_configuration_are_recorded():
    model = load_model_text(
        "param room.x = 1 cm in [-10 cm, 10 cm] sigma 2 mm\nparam q[1..3] = 0 deg per configuration\n"
    )
    p = model.param("room.x")
    assert (p.nominal, p.lower, p.upper, p.sigma) == pytest.approx((0.01, -0.1, 0.1, 0.002))
    assert not p.per_configuration
    assert model.names("param")[1:] == ["q1", "q2", "q3"]
    assert model.param("q2").per_configuration
    assert model.param("q2").unit == "deg"


def test_arithmetic_and_functions_are_evaluated_without_eval():
    text = """
    param a = 3 m
    param t = 30 deg
    let s = sqrt(a * a + 16 m * 1 m)        # 5 m
    frame f at translate(s, a * sin(t) + 2^3 * 1 cm, -(1 m - 2 m) / 4) {
      point p = (max(1 m, 2 m) - abs(-0.5 m), atan2(1 m, 1 m) / (pi * 1 rad) * 1 m, hypot(3 m, 4 m))
      point q = (cos(t) * 1 m, tan(45 deg) * 1 m, asin(0.5) / 1 rad * 1 m)
    }
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    T = np.asarray(scene.frame("f"))
    np.testing.assert_allclose(T[:3, 3], [5.0, 1.5 + 0.08, 0.25])
    np.testing.assert_allclose(np.asarray(scene.point("f.p")) - T[:3, 3], [1.5, 0.25, 5.0])
    np.testing.assert_allclose(np.asarray(scene.point("f.q")) - T[:3, 3], [math.cos(math.pi / 6), 1.0, math.pi / 6])


def test_operator_precedence_unary_minus_binds_looser_than_power():
    model = load_model_text("frame f at translate(-2^2 * 1 m, 2 * 3 + 4 * 1 m, 2^3^2 / 512 * 1 m)")
    T = np.asarray(modeler(model, model.nominal).frame("f"))
    np.testing.assert_allclose(T[:3, 3], [-4.0, 10.0, 1.0])


def test_comments_semicolons_and_newlines_are_free():
    a = load_model_text("param a = 1 m # a comment\nframe f at (a, 0, 0) { point p = (0, 0, 0); point q = (1, 0, 0) }")
    b = load_model_text("param a = 1 m frame f at (a, 0, 0) {\npoint p = (0, 0, 0)\npoint q = (1, 0, 0)\n}")
    assert a.names("point") == b.names("point") == ["f.p", "f.q"]


def test_syntax_tree_ignores_positions_when_compared():
    assert parse_text("param a = 1 m", "x.mdl") == parse_text("\n\n   param a =   1 m", "y.mdl")


def test_templates_take_positional_keyword_and_default_arguments():
    text = """
    template pipe(length, radius = 2 cm) {
      shape tube(radius, radius - 3 mm, length)
      point end_a = (0, 0, -length / 2)
      point end_b = (0, 0, length / 2)
    }
    object a = pipe(1 m) at (0, 1 m, 0)
    object b = pipe(radius = 4 cm, length = 50 cm) at (0, 2 m, 0) { point mark = (4 cm, 0, 0) }
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    np.testing.assert_allclose(np.asarray(scene.point("a.end_b")), [0, 1, 0.5])
    np.testing.assert_allclose(np.asarray(scene.point("b.end_a")), [0, 2, -0.25])
    np.testing.assert_allclose(np.asarray(scene.point("b.mark")), [0.04, 2, 0])
    dims = np.asarray(scene.shape_dims)
    np.testing.assert_allclose(dims[0], [0.02, 0.017, 1.0])
    np.testing.assert_allclose(dims[1], [0.04, 0.037, 0.5])


def test_parameters_declared_in_a_template_are_prefixed_per_instance():
    text = """
    template fan(r) {
      param angle = 0 deg in [0 deg, 90 deg]
      object blade at rot_z(angle) { point tip = (r, 0, 0) }
    }
    object left = fan(10 cm)
    object right = fan(20 cm) at (1 m, 0, 0)
    """
    model = load_model_text(text)
    assert model.names("param") == ["left.angle", "right.angle"]
    scene = modeler(model, {"right.angle": math.pi / 2})
    np.testing.assert_allclose(np.asarray(scene.point("left.blade.tip")), [0.1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(np.asarray(scene.point("right.blade.tip")), [1.0, 0.2, 0], atol=1e-12)


def test_template_body_does_not_see_the_callers_lets():
    text = "template t() { point p = (secret, 0, 0) }\nframe f { let secret = 1 m\n object x = t() }"
    with pytest.raises(errors.UndefinedNameError):
        load_model_text(text)


def test_names_resolve_relative_to_enclosing_frames_first():
    text = """
    param x = 5 m
    frame room {
      param x = 1 m               # room.x
      point p = (x, 0, 0)         # finds room.x, not the top-level x
      point q = (room.x + 0 m, 0, 0)
    }
    point top = (x, 0, 0)
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    assert float(scene.point("room.p")[0]) == 1.0
    assert float(scene.point("room.q")[0]) == 1.0
    assert float(scene.point("top")[0]) == 5.0


def test_include_brings_templates_and_parameters(write_model):
    write_model("template marker() { point m = (0, 0, 1 cm) }\nparam shared.h = 2 m\n", "lib/parts.mdl")
    path = write_model('include "lib/parts.mdl"\nobject a = marker() at (0, 0, shared.h)\n')
    model = load_model(path)
    np.testing.assert_allclose(np.asarray(modeler(model, model.nominal).point("a.m")), [0, 0, 2.01])
    assert len(model.files) == 2


def test_an_override_in_a_file_replaces_one_in_a_file_it_includes_wherever_it_stands(write_model):
    """A site's model re-sets what an included calibration file set (its own override wins,
    value and prior σ, before or after the include and through several levels)."""
    write_model("param a = 1 m sigma 1 cm\noverride a = 2 m sigma 2 cm\n", "lib/robot_cal.mdl")
    write_model('include "robot_cal.mdl"\noverride a = 3 m\n', "lib/robot.mdl")
    assert load_model(write_model('include "lib/robot_cal.mdl"\n')).param("a").sigma == pytest.approx(0.02)
    for text in ('override a = 4 m\ninclude "lib/robot.mdl"\n', 'include "lib/robot.mdl"\noverride a = 4 m\n'):
        info = load_model(write_model(text)).param("a")
        assert (info.nominal, info.sigma, info.value_span.path) == (4.0, pytest.approx(0.01), "model.mdl")
    assert load_model(write_model('include "lib/robot.mdl"\n')).param("a").nominal == 3.0


def test_include_inside_a_frame_mounts_the_file_under_it(write_model):
    write_model("param q = 0 deg\nobject stick at rot_x(q) { point tip = (0, 0, 1 m) }\n", "stick.mdl")
    path = write_model('frame base at (1 m, 0, 0) { include "stick.mdl" }\n')
    model = load_model(path)
    assert model.names("param") == ["base.q"]
    scene = modeler(model, {"base.q": -math.pi / 2})
    np.testing.assert_allclose(np.asarray(scene.point("base.stick.tip")), [1, 1, 0], atol=1e-12)


def test_meshes_load_relative_to_the_model_file_with_scale(write_model, tmp_path):
    import trimesh

    (tmp_path / "meshes").mkdir()
    trimesh.creation.box(extents=(1, 2, 3)).export(tmp_path / "meshes" / "part.stl")
    write_model('frame f {\n  shape part = mesh("../meshes/part.stl", scale = 0.5)\n}\n', "sub/model.mdl")
    model = load_model("sub/model.mdl")
    shape = model.shapes[0]
    assert shape.kind == "mesh" and shape.name == "f.part"
    scene = modeler(model, model.nominal)
    bounds = scene.to_trimesh().bounds
    np.testing.assert_allclose(bounds, [[-0.25, -0.5, -0.75], [0.25, 0.5, 0.75]], atol=1e-9)


def test_a_mesh_is_read_with_trimesh_once_then_from_the_cache_folder(write_model, tmp_path, monkeypatch):
    # import trimesh alone took ~0.6 s of every command on a model with a mesh (issue 16): the
    # triangles are kept in the cache folder, keyed by the file's bytes.
    import json
    import os
    import subprocess
    import sys

    import trimesh

    cache = tmp_path / "cache"
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(cache))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    part = tmp_path / "part.obj"
    trimesh.creation.box(extents=(1, 2, 3)).export(part)
    path = write_model('frame f {\n  shape part = mesh("part.obj")\n}\n')
    mesh = load_model(path).shapes[0].mesh
    direct = trimesh.load(str(part), force="mesh", process=False)
    np.testing.assert_array_equal(mesh.vertices, direct.vertices)
    np.testing.assert_array_equal(mesh.faces, direct.faces)
    entries = sorted((cache / "meshes").glob("*.npz"))
    assert len(entries) == 1

    code = (
        "import json, sys; from mbcal.language import load_model; "
        f"mesh = load_model({str(tmp_path / path)!r}).shapes[0].mesh; "
        "print(json.dumps({'trimesh': 'trimesh' in sys.modules, "
        "'v': mesh.vertices.tolist(), 'f': mesh.faces.tolist()}))"
    )
    env = {**os.environ, "MBCAL_CACHE_DIR": str(cache)}
    out = json.loads(
        subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    )
    assert out["trimesh"] is False  # a second process reads the arrays, without trimesh
    np.testing.assert_array_equal(out["v"], mesh.vertices)
    np.testing.assert_array_equal(out["f"], mesh.faces)

    entries[0].write_bytes(b"not an npz file")  # a spoilt entry: the file is read again, the entry rewritten
    np.testing.assert_array_equal(load_model(path).shapes[0].mesh.vertices, mesh.vertices)
    assert np.load(entries[0])["faces"].shape == mesh.faces.shape

    trimesh.creation.box(extents=(4, 4, 4)).export(part)  # a changed file is a new entry
    np.testing.assert_allclose(np.ptp(load_model(path).shapes[0].mesh.vertices, axis=0), [4, 4, 4])
    assert len(list((cache / "meshes").glob("*.npz"))) == 2

    from mbcal.language import meshes

    reader = meshes._reader
    monkeypatch.setattr(meshes, "_reader", lambda: "trimesh 99.0")  # another trimesh: a new entry
    np.testing.assert_allclose(np.ptp(load_model(path).shapes[0].mesh.vertices, axis=0), [4, 4, 4])
    assert len(list((cache / "meshes").glob("*.npz"))) == 3
    monkeypatch.setattr(meshes, "_reader", reader)

    read = meshes._read_with_trimesh

    def saved_again_meanwhile(path, span):  # an editor saves the file while trimesh reads it
        got = read(path, span)
        trimesh.creation.box(extents=(6, 6, 6)).export(part)
        return got

    trimesh.creation.box(extents=(3, 3, 3)).export(part)
    monkeypatch.setattr(meshes, "_read_with_trimesh", saved_again_meanwhile)
    load_model(path)
    assert len(list((cache / "meshes").glob("*.npz"))) == 3  # not kept under the old content's key
    monkeypatch.setattr(meshes, "_read_with_trimesh", read)
    np.testing.assert_allclose(np.ptp(load_model(path).shapes[0].mesh.vertices, axis=0), [6, 6, 6])
    assert len(list((cache / "meshes").glob("*.npz"))) == 4

    gltf = tmp_path / "part.gltf"  # a .gltf's vertices are in a buffer file of their own: never kept
    gltf.write_bytes(trimesh.creation.box(extents=(1, 1, 1)).export(file_type="gltf")["model.gltf"])
    assert meshes._entry(gltf, ".gltf") is None and meshes._entry(part, ".obj") is not None

    monkeypatch.setenv("MBCAL_CACHE", "off")  # caching off: read with trimesh, nothing written
    trimesh.creation.box(extents=(5, 5, 5)).export(part)
    np.testing.assert_allclose(np.ptp(load_model(path).shapes[0].mesh.vertices, axis=0), [5, 5, 5])
    assert len(list((cache / "meshes").glob("*.npz"))) == 4


def test_a_model_file_is_parsed_with_lark_once_then_read_from_the_cache_folder(write_model, tmp_path, monkeypatch):
    # Lark's import, its tables and the parse were ~0.06 s of every command that loads a model
    # (issue 16): the statements of a file that parsed are kept, keyed by its text and path.
    import json
    import os
    import subprocess
    import sys

    from mbcal.language import parse

    cache = tmp_path / "cache"
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(cache))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    text = "param a = 1 m in [0, 2 m]\nframe f at (a, 0, 0) {\n  point p = (0, 0, 1 m)\n}\n"
    path = write_model(text)
    first = parse.parse_file(path)
    entries = sorted((cache / "syntax").glob("*.json"))
    assert len(entries) == 1
    same = parse._to_json  # the spans too (a node's == leaves them out)
    assert same(parse.parse_file(path)) == same(first) == same(parse.parse_text(text, str(path)))  # what Lark gives

    code = (
        "import json, sys; from mbcal.language import load_model; "
        f"m = load_model({str(tmp_path / path)!r}); "
        "print(json.dumps({'lark': 'lark' in sys.modules, 'nominal': m.nominal.tolist()}))"
    )
    env = {**os.environ, "MBCAL_CACHE_DIR": str(cache)}
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    out = json.loads(run.stdout)
    assert out == {"lark": False, "nominal": [1.0]}  # a second process: no Lark
    assert len(list((cache / "syntax").glob("*.json"))) == 1

    # A later check still shows the offending line from a model read from the cache.
    broken = write_model(text + "point q = (b, 0, 0)\n", name="broken.mdl")
    parse.parse_file(broken)  # parses (the undefined name is the checker's error), kept
    errors._SOURCES.pop(broken, None)
    with monkeypatch.context() as patch:
        patch.setattr(parse, "parse_text", lambda *a: pytest.fail("parsed again"))
        with pytest.raises(errors.UndefinedNameError) as err:
            load_model(broken)
    assert "broken.mdl:5:12: undefined name 'b'" in str(err.value)
    assert "point q = (b, 0, 0)" in err.value.render()
    assert errors._SOURCES[broken] == text + "point q = (b, 0, 0)\n"  # remembered, as a parse does

    # A syntax error is not kept, and is the same error every time.
    bad = write_model("frame f at (0, 0 {\n}\n", name="bad.mdl")
    count = len(list((cache / "syntax").glob("*.json")))
    messages = []
    for _ in range(2):
        with pytest.raises(errors.MdlSyntaxError) as err:
            parse.parse_file(bad)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "bad.mdl:1:" in messages[0]
    assert len(list((cache / "syntax").glob("*.json"))) == count

    # The same text under another path is another entry: the spans name the file they are in.
    other = write_model(text, name="other.mdl")
    assert parse.parse_file(other)[0].span.path.endswith("other.mdl")
    assert parse.parse_file(path)[0].span.path.endswith(path)

    # A spoilt entry is parsed again and rewritten; another grammar or parser code is a new key.
    for spoilt in (b"not JSON", b'[{"@": "Popen", "args": "touch x"}]', b'[{"@": "Param", "name": "a"}]'):
        entries[0].write_bytes(spoilt)  # not JSON; a class that is no syntax-tree node; other fields
        assert same(parse.parse_file(path)) == same(first)
        assert entries[0].read_bytes() != spoilt
    code = parse._syntax_code
    monkeypatch.setattr(parse, "_syntax_code", lambda: b"another grammar")
    before = len(list((cache / "syntax").glob("*.json")))
    assert parse.parse_file(path) == first
    assert len(list((cache / "syntax").glob("*.json"))) == before + 1
    monkeypatch.setattr(parse, "_syntax_code", code)

    # Bounded: writing one more beyond the limit removes the least recently used (a hit counts as a
    # use), and only the part's own entries (the folder may hold the user's files).
    monkeypatch.setattr(parse, "_SYNTAX_ENTRIES", 4)
    monkeypatch.setattr(parse, "_SYNTAX_KEEP", 2)
    users = cache / "syntax" / "notes.json"
    users.write_text("the user's")
    parsed = []
    lark = parse.parse_text
    monkeypatch.setattr(parse, "parse_text", lambda text, where: parsed.append(where) or lark(text, where))
    for k in range(6):
        parse.parse_file(write_model(text + f"param extra{k} = {k}\n", name=f"m{k}.mdl"))
        parse.parse_file(path)  # used again each time: kept
    assert parsed == [f"m{k}.mdl" for k in range(6)]  # never model.mdl again
    assert len(list((cache / "syntax").glob("*.json"))) <= 4 + 1
    assert users.read_text() == "the user's"
    monkeypatch.setattr(parse, "parse_text", lark)

    monkeypatch.setenv("MBCAL_CACHE", "off")  # caching off: parsed with Lark, nothing written
    kept = sorted((cache / "syntax").glob("*.json"))
    assert parse.parse_file(write_model(text + "param off = 1\n", name="off.mdl"))
    assert sorted((cache / "syntax").glob("*.json")) == kept


def test_range_sensor_directions_are_normalised():
    model = load_model_text(
        "range a(direction = (0, 0, 2))\nrange b(directions = [(1, 0, 0), (0, 3, 4)])\n"
        "range c(fov = (40 deg, 30 deg), rays = (4, 3), max = 5 m)\n"
    )
    np.testing.assert_allclose(model.ranges[0].directions, [[0, 0, 1]])
    np.testing.assert_allclose(model.ranges[1].directions, [[1, 0, 0], [0, 0.6, 0.8]])
    assert model.ranges[2].directions.shape == (12, 3)
    assert model.ranges[2].max_range == 5.0
    np.testing.assert_allclose(np.linalg.norm(model.ranges[2].directions, axis=1), 1.0)


def test_a_single_row_or_column_of_rays_may_span_up_to_a_full_turn():
    def angles(text):  # each ray's angle from +z, in degrees
        d = load_model_text(text).ranges[0].directions
        return np.degrees(np.arctan2(d[:, 0] + d[:, 1], d[:, 2]))

    # a 2-D lidar of 270 deg: rays by angle, not by tan (which folded them back past 90 deg)
    np.testing.assert_allclose(angles("range l(fov = (270 deg, 0 deg), rays = (7, 1))"), np.arange(-135, 136, 45))
    d = load_model_text("range l(fov = (0 deg, 120 deg), rays = (1, 3))").ranges[0].directions
    np.testing.assert_allclose(d, [[0, -np.sqrt(3) / 2, 0.5], [0, 0, 1], [0, np.sqrt(3) / 2, 0.5]], atol=1e-15)
    # a full turn: n rays 360/n deg apart, the first (straight back) not repeated
    np.testing.assert_allclose(angles("range l(fov = (360 deg, 0 deg), rays = (4, 1))"), [-180, -90, 0, 90])
    # below 180 deg a single row gets the rays of the grid rule (tan a, 0, 1)
    a = np.radians(np.linspace(-80, 80, 5))
    d = np.stack([np.tan(a), np.zeros(5), np.ones(5)], axis=1)
    np.testing.assert_allclose(
        load_model_text("range l(fov = (160 deg, 0 deg), rays = (5, 1))").ranges[0].directions,
        d / np.linalg.norm(d, axis=1, keepdims=True),
        rtol=0,
        atol=1e-15,
    )
    with pytest.raises(errors.DimensionError, match=r"^<string>:1:15: a single row of rays spans at most 360 deg"):
        load_model_text("range l(fov = (400 deg, 0 deg), rays = (8, 1))")


def test_camera_intrinsics_and_distortion_may_be_parameters():
    text = """
    param cam.f = 800 in [600, 1000]
    param cam.k1 = -0.2
    camera c(width = 640, height = 480, f = cam.f, cx = 320, cy = 240, k1 = cam.k1, p2 = 0.001)
    """
    model = load_model_text(text)
    scene = modeler(model, {"cam.f": 900.0})
    view = scene.camera("c")
    np.testing.assert_allclose(np.asarray(view.intrinsics), [900, 900, 320, 240, 0])
    np.testing.assert_allclose(np.asarray(view.distortion), [-0.2, 0, 0, 0.001, 0])


def test_unnamed_shapes_never_take_a_name_written_in_their_frame():
    """An unnamed shape is shapeN by its place among the frame's shapes, but skips a name declared
    in the frame: 'shape shape1 = ...' and an unnamed second shape were both f.shape1 (the scene
    said 3 shapes, its glTF held 2 nodes)."""
    model = load_model_text(
        "frame f {\n  shape shape1 = sphere(2 m)\n  shape sphere(1 m)\n  shape sphere(1 m)\n}\n"
        "frame g {\n  shape sphere(1 m)\n  point shape1 = (0, 0, 0)\n  shape box(1, 1, 1)\n"
        "  shape shape3 = sphere(2 m)\n  shape sphere(1 m)\n}\n"
    )
    assert model.names("shape") == ["f.shape1", "f.shape2", "f.shape3", "g.shape0", "g.shape2", "g.shape3", "g.shape4"]
    with pytest.raises(errors.DuplicateNameError, match=r"^<string>:1:40: 'f.a' is already declared at <string>:1:17"):
        load_model_text("frame f { shape a = sphere(2 m); shape a = sphere(1 m) }")


def test_chessboard_target_names_corners_row_by_row():
    model = load_model_text("target board = chessboard(rows = 2, cols = 3, square = 25 mm) at (1 m, 0, 0)")
    assert model.names("point") == [f"board.r{r}c{c}" for r in range(2) for c in range(3)]
    scene = modeler(model, model.nominal)
    np.testing.assert_allclose(np.asarray(scene.point("board.r1c2")), [1.05, 0.025, 0])


def test_measure_statement_lists_measurement_models():
    assert load_model_text("measure image_point, range\nmeasure distance").measures == (
        "image_point",
        "range",
        "distance",
    )


def test_unique_suffix_finds_a_deep_name():
    model = load_model(MODELS / "arm7.mdl")
    assert model.resolve("point", "hand.tip").endswith(".wrist_flexion.hand.tip")
    with pytest.raises(errors.UnknownNameError, match="ambiguous"):
        model.resolve("shape", "bone")


def test_grammar_is_one_file_in_the_checkout():
    assert grammar_path().name == "mdl.lark"
    assert "start:" in grammar_path().read_text()
