"""Every kind of bad model input gets a typed error with its exact location and message."""

from __future__ import annotations

import pytest

from mbcal import errors
from mbcal.language import load_model, load_model_text

# name → (model text, error type, exact "path:line:col: message" as str(error))
GOLDEN = {
    "syntax_missing_value": (
        "param x = \n",
        errors.MdlSyntaxError,
        "model.mdl:1:11: unexpected end of file; expected '(', '+', '-', '[', a name, a number, a string",
    ),
    "syntax_unclosed_paren": (
        "frame a {\n  point p = (1, 2\n}\n",
        errors.MdlSyntaxError,
        "model.mdl:3:1: unexpected '}'; expected ')', ',', ']'",
    ),
    "syntax_unexpected_character": (
        "param x = 3 m $\n",
        errors.MdlSyntaxError,
        "model.mdl:1:15: unexpected character '$'; expected ')', '*', '+', '+-', ',', '-', '/', ';', ...",
    ),
    "undefined_name_suggests": (
        "param lever.angle = 0 deg\nframe a {\n  joint revolute(z, lever.angel)\n}\n",
        errors.UndefinedNameError,
        "model.mdl:3:21: undefined name 'lever.angel' (did you mean 'lever.angle'?)",
    ),
    "undefined_template": (
        "template pipe(length) { shape cylinder(1 cm, length) }\nobject p = pipes(1 m)\n",
        errors.UndefinedNameError,
        "model.mdl:2:12: no template named 'pipes' (did you mean 'pipe'?)",
    ),
    "duplicate_parameter": (
        "param a = 1 m\nparam a = 2 m\n",
        errors.DuplicateNameError,
        "model.mdl:2:7: parameter 'a' is already declared at model.mdl:1:1",
    ),
    "duplicate_point": (
        "frame f {\n  point p = (0, 0, 0)\n  point p = (1, 0, 0)\n}\n",
        errors.DuplicateNameError,
        "model.mdl:3:9: 'f.p' is already declared at model.mdl:2:9",
    ),
    "let_with_the_name_of_a_parameter": (
        "param x = 1 m in [0 m, 2 m]\nlet x = 5 cm\npoint p = (x, 0, 0)\n",
        errors.DuplicateNameError,
        "model.mdl:2:5: let 'x' has the name of parameter 'x' declared at model.mdl:1:1 "
        "(a name means one thing in a scope: rename one of them)",
    ),
    "template_argument_twice": (
        "template t(a, a) { point p = (a, 0, 0) }\nobject o = t(1 m, 2 m)\n",
        errors.DuplicateNameError,
        "model.mdl:1:15: argument 'a' of template 't' is already declared at model.mdl:1:12",
    ),
    "unit_mismatch_in_sum": (
        "param a = 1 m + 30 deg\n",
        errors.UnitError,
        "model.mdl:1:11: cannot add a length (m) and an angle (rad)",
    ),
    "angle_where_length_expected": (
        "frame f at translate(0, 30 deg, 0)\n",
        errors.UnitError,
        "model.mdl:1:25: translate() argument 'y' must be a length (m), got an angle (rad)",
    ),
    "length_where_angle_expected": (
        "param len = 10 cm\nframe f at rot_z(len)\n",
        errors.UnitError,
        "model.mdl:2:18: rot_z() angle must be an angle (rad), got a length (m)",
    ),
    "too_few_arguments": (
        "frame f {\n  shape box(1 m, 2 m)\n}\n",
        errors.ArgumentError,
        "model.mdl:2:3: box() is missing argument 'sz'",
    ),
    "too_many_template_arguments": (
        "template pipe(length) { shape cylinder(1 cm, length) }\nobject p = pipe(1 m, 2 m, 3 m)\n",
        errors.ArgumentError,
        "model.mdl:2:22: template pipe() takes 1 argument (length) but 3 were given",
    ),
    "unknown_keyword_argument": (
        "frame f {\n  shape tube(outer = 3 cm, inner = 2 cm, lenght = 1 m)\n}\n",
        errors.ArgumentError,
        "model.mdl:2:42: tube() has no argument 'lenght' (it takes outer, inner, length) (did you mean 'length'?)",
    ),
    "negative_dimension": (
        "frame f {\n  shape sphere(-2 cm)\n}\n",
        errors.DimensionError,
        "model.mdl:2:16: sphere() dimension 'radius' must be positive, got -0.02 m at the nominal values",
    ),
    "tube_inner_larger_than_outer": (
        "frame f {\n  shape tube(2 cm, 3 cm, 1 m)\n}\n",
        errors.DimensionError,
        "model.mdl:2:20: a tube's inner radius (0.03 m) must be smaller than its outer radius (0.02 m)",
    ),
    "unknown_shape": (
        "frame f {\n  shape cilinder(1 cm, 1 m)\n}\n",
        errors.UndefinedNameError,
        "model.mdl:2:9: unknown shape 'cilinder' (one of box, cylinder, cone, sphere, tube, rectangle, plane, mesh)"
        " (did you mean 'cylinder'?)",
    ),
    "unknown_function": (
        "frame f at rotz(30 deg)\n",
        errors.UndefinedNameError,
        "model.mdl:1:12: unknown function 'rotz' (did you mean 'rot_z', 'rot_y', 'rot_x'?)",
    ),
    "joint_outside_a_frame": (
        "param q = 0 deg\njoint revolute(z, q)\n",
        errors.MdlError,
        "model.mdl:2:1: a joint moves a frame: put it inside 'frame NAME { ... }'",
    ),
    "two_joints_in_one_frame": (
        "param q = 0 deg\nframe f {\n  joint revolute(z, q)\n  joint revolute(x, q)\n}\n",
        errors.DuplicateNameError,
        "model.mdl:4:3: frame 'f' already has a joint at model.mdl:3:3",
    ),
    "parameter_value_not_constant": (
        "param a = 1 m\nparam b = a * 2\n",
        errors.MdlError,
        "model.mdl:2:11: the nominal value of parameter 'b' must be a constant, but it depends on parameter 'a'",
    ),
    "let_cycle": (
        "let a = b\nlet b = a\nframe f at translate(a, 0, 0)\n",
        errors.MdlError,
        "model.mdl:2:9: let 'a' is defined in terms of itself: a -> b -> a",
    ),
    "template_recursion": (
        "template t() { object inner = t() }\nobject x = t()\n",
        errors.MdlError,
        "model.mdl:1:16: template instantiates itself: t -> t",
    ),
    "vector_where_number_expected": (
        "frame f {\n  shape sphere((1, 2, 3))\n}\n",
        errors.MdlTypeError,
        "model.mdl:2:16: sphere() argument 'radius' must be a scalar, got a 3-vector",
    ),
    "camera_without_size": (
        "camera c(f = 500)\n",
        errors.ArgumentError,
        "model.mdl:1:1: camera 'c' needs 'width' (image size in pixels)",
    ),
    "camera_wider_than_a_renderer_draws": (
        "camera c(width = 16385, height = 100, f = 600)\n",
        errors.DimensionError,
        "model.mdl:1:18: the camera's width must be a whole number of pixels in 1..16384, got 16385",
    ),
    "camera_of_infinite_height": (
        "camera c(width = 640, height = 1 / 0, f = 600)\n",
        errors.DimensionError,
        "model.mdl:1:32: the camera's height must be a whole number of pixels in 1..16384, got inf",
    ),
    "grid_of_rays_of_180_deg": (
        "range lidar(fov = (180 deg, 30 deg), rays = (16, 4))\n",
        errors.DimensionError,
        "model.mdl:1:19: a grid of rays needs a horizontal field of view below 180 deg, got 180 deg "
        "(only a single row or column of rays (rays = (n, 1) or (1, n)) may span up to 360 deg)",
    ),
    "override_that_overflows": (
        "param lever.angle = 0 rad\noverride lever.angle = 1e308 rad * 10\n",
        errors.DimensionError,
        "model.mdl:2:24: the override of 'lever.angle' is not a finite number",
    ),
    "override_that_is_nan": (
        "param a = 1 m\noverride a = 0 m / 0\n",
        errors.DimensionError,
        "model.mdl:2:14: the override of 'a' is not a finite number",
    ),
    "override_sigma_that_overflows": (
        "param a = 1 m\noverride a = 2 m sigma 1e308 m * 10\n",
        errors.DimensionError,
        "model.mdl:2:24: the sigma of the override of 'a' is not a finite number",
    ),
    "search_range_that_overflows": (
        "param a = 1 m in [0 m, 1e308 m * 10]\n",
        errors.DimensionError,
        "model.mdl:1:24: the upper end of the search range of 'a' is not a finite number",
    ),
    "sigma_that_overflows": (
        "param a = 1 m sigma 1e308 m * 10\n",
        errors.DimensionError,
        "model.mdl:1:21: the sigma of 'a' is not a finite number",
    ),
    "camera_centre_that_is_infinite": (
        "camera c(width = 640, height = 480, f = 500, cx = 1 / 0, k1 = 0 / 0)\n",
        errors.DimensionError,
        "model.mdl:1:51: camera 'c': cx is not a finite number at the nominal values",
    ),
    "camera_distortion_that_is_nan": (
        "param k = 0\ncamera c(width = 640, height = 480, f = 500, k1 = k / 0)\n",
        errors.DimensionError,
        "model.mdl:2:51: camera 'c': k1 is not a finite number at the nominal values",
    ),
    "joint_offset_that_is_infinite": (
        "param q = 0 deg\nframe l {\n  joint revolute(z, q, offset = 1 rad / 0)\n}\n",
        errors.DimensionError,
        "model.mdl:3:33: the offset of the joint of 'l' is not finite at the nominal values",
    ),
    "joint_limit_that_overflows": (
        "param q = 0 deg\nframe l {\n  joint revolute(z, q, upper = 1e308 rad * 10)\n}\n",
        errors.DimensionError,
        "model.mdl:3:32: the joint's upper limit is not a finite number",
    ),
    "range_that_overflows": (
        "range r(direction = (0, 0, 1), max = 1e308 m * 10)\n",
        errors.DimensionError,
        "model.mdl:1:38: the maximum range must be a positive finite constant",
    ),
    "camera_with_f_and_fx": (
        "camera c(width = 640, height = 480, f = 500, fx = 400)\n",
        errors.ArgumentError,
        "model.mdl:1:51: camera 'c' takes f = ... or fx = ..., fy = ..., not both "
        "(f is the focal length of both axes: drop it, or drop fx and fy)",
    ),
    "camera_with_fx_alone": (
        "camera c(width = 640, height = 480, fx = 500)\n",
        errors.ArgumentError,
        "model.mdl:1:42: camera 'c' has fx but no fy: give both (or f = ... for both)",
    ),
    "look_at_straight_down_along_up": (
        "camera top(width = 640, height = 480, f = 500) at look_at(eye = (0, 0, 2 m), target = (0, 0, 0))\n",
        errors.DimensionError,
        "model.mdl:1:51: look_at()'s view from eye to target is parallel to its up = z, so the camera's x axis "
        "(perpendicular to both) is undefined (give look_at another up = ... (up = y, say, for a view straight "
        "down or up))",
    ),
    "look_at_along_up_at_the_nominal_values": (
        "param h = 2 m\nframe top at rot_z(0 deg) * look_at(eye = (0, 0, h), target = (0, 0, 0), up = -z)\n",
        errors.DimensionError,
        "model.mdl:2:29: the pose of 'top' is not finite at the nominal values: look_at()'s view from eye to target "
        "is parallel to its up = -z, so the camera's x axis (perpendicular to both) is undefined (give look_at "
        "another up = ... (up = y, say, for a view straight down or up))",
    ),
    "look_at_its_own_eye": (
        "frame top at look_at(eye = (0, 0, 2 m), target = (0, 0, 2 m))\n",
        errors.DimensionError,
        "model.mdl:1:14: look_at()'s eye and target are the same point: there is no direction to look in",
    ),
    "empty_search_range": (
        "param a = 0 m in [1 m, -1 m]\n",
        errors.DimensionError,
        "model.mdl:1:19: empty search range [1 m, -1 m] for 'a' (lower bound above upper)",
    ),
    "reserved_word_as_name": (
        "frame at { }\n",
        errors.MdlError,
        "model.mdl:1:7: 'at' is a reserved word and cannot name a frame",
    ),
    "let_named_inf": (
        "let inf = 5 m\nparam a = 1 m limits [0 m, inf]\n",
        errors.MdlError,
        "model.mdl:1:5: 'inf' is a reserved word and cannot name a let",
    ),
    "parameter_name_ending_in_pi": (
        "param f.pi = 3\nframe f { point p = (pi, 0, 0) }\n",
        errors.MdlError,
        "model.mdl:1:7: 'pi' is a reserved word and cannot end a parameter name: 'f.pi'",
    ),
    "let_named_like_an_axis": (
        "param q = 0 deg\nlet z = (1, 0, 0)\nframe f { joint revolute(z, q) }\n",
        errors.MdlError,
        "model.mdl:2:5: 'z' is the z axis where an axis is written (joint, axis_angle, look_at's up) and cannot "
        "name a let (give the let another name; an axis may be any 3-vector: joint revolute(my_axis, q))",
    ),
    "template_argument_named_like_an_axis": (
        "template hinge(x) { joint revolute(x, 0 deg) }\nobject h = hinge((0, 1, 0))\n",
        errors.MdlError,
        "model.mdl:1:16: 'x' is the x axis where an axis is written (joint, axis_angle, look_at's up) and cannot "
        "name a template argument (give the template argument another name; an axis may be any 3-vector: "
        "joint revolute(my_axis, q))",
    ),
    "vector_plus_transform": (
        "frame f at (1 m, 0, 0) + rot_z(10 deg)\n",
        errors.MdlTypeError,
        "model.mdl:1:12: cannot add a 3-vector and a transform",
    ),
    "transform_times_a_number": (
        "frame f at rot_z(10 deg) * 2\n",
        errors.MdlTypeError,
        "model.mdl:1:12: cannot multiply a transform by a scalar (a transform is multiplied by a transform, or by a "
        "position (x, y, z) that stands for a translation)",
    ),
    "template_called_as_a_function": (
        "template t(a) { point p = (a, 0, 0) }\npoint q = t(1 m)\n",
        errors.MdlTypeError,
        "model.mdl:2:11: 't' is a template, not a function (a template is instantiated as a frame: "
        "object NAME = t(...))",
    ),
    "nul_byte_at_its_column": (
        "param a = 1 m\nparam b = 2 m \x00\n",
        errors.MdlSyntaxError,
        "model.mdl:2:15: file contains a NUL byte (is it a binary file?)",
    ),
    "sum_of_300_terms": (
        "param a = 1 m\nparam b = " + " + ".join(["1 m"] * 300) + "\n",
        errors.MdlSyntaxError,
        "model.mdl:2:11: expression too deep: more than 300 levels of operators, calls and vectors (each operator "
        "of a chain a + b + c + ... is one) (split it with lets: let part1 = a + b + ...)",
    ),
    "sigma_with_wrong_unit": (
        "param a = 0 m sigma 1 deg\n",
        errors.UnitError,
        "model.mdl:1:21: the sigma of 'a' is an angle (rad) but its value is a length (m)",
    ),
    "override_twice_in_one_file": (
        "param a = 1 m\noverride a = 2 m\noverride a = 3 m\n",
        errors.DuplicateNameError,
        "model.mdl:3:10: 'a' is already overridden at model.mdl:2:1 "
        "(an override replaces only one in a file it includes)",
    ),
    "pose_that_is_not_a_transform": (
        "param a = 1 m\nframe f at a\n",
        errors.MdlTypeError,
        "model.mdl:2:12: 'at' needs a transform (translate(...), rot_z(...), ...) or a position (x, y, z), "
        "got a scalar",
    ),
}


@pytest.mark.parametrize("case", sorted(GOLDEN))
def test_bad_model_gives_exact_located_error(case, write_model):
    text, error_type, expected = GOLDEN[case]
    path = write_model(text)
    with pytest.raises(error_type) as info:
        load_model(path)
    assert str(info.value) == expected
    assert isinstance(info.value, errors.MdlError)


def test_rendered_error_shows_source_line_and_caret(write_model):
    path = write_model("param len = 10 cm\nframe f at rot_z(len)\n")
    with pytest.raises(errors.UnitError) as info:
        load_model(path)
    lines = info.value.render().splitlines()
    assert lines[0] == "model.mdl:2:18: rot_z() angle must be an angle (rad), got a length (m)"
    assert lines[1] == "    frame f at rot_z(len)"
    assert lines[2] == "    " + " " * 17 + "^^^"


def test_missing_include_names_the_including_file(write_model):
    path = write_model('include "parts/nothere.mdl"\n')
    with pytest.raises(errors.IncludeError) as info:
        load_model(path)
    assert str(info.value).startswith("model.mdl:1:1: file not found: ")
    assert str(info.value).endswith("parts/nothere.mdl")


def test_error_inside_included_file_names_that_file(write_model):
    write_model("param a = 1 m + 2 deg\n", "parts/bad.mdl")
    path = write_model('include "parts/bad.mdl"\n')
    with pytest.raises(errors.UnitError) as info:
        load_model(path)
    assert str(info.value) == "parts/bad.mdl:1:11: cannot add a length (m) and an angle (rad)"


def test_overrides_in_two_files_neither_of_which_includes_the_other_are_an_error(write_model):
    write_model("param a = 1 m\noverride a = 2 m\n", "left.mdl")
    write_model("override a = 3 m\n", "right.mdl")
    path = write_model('include "left.mdl"\ninclude "right.mdl"\n')
    with pytest.raises(errors.DuplicateNameError) as info:
        load_model(path)
    assert str(info.value) == (
        "right.mdl:1:10: 'a' is already overridden at left.mdl:2:1 "
        "(an override replaces only one in a file it includes)"
    )


def test_an_override_an_including_file_replaces_is_still_checked(write_model):
    write_model("param a = 1 m limits [0 m, 5 m]\noverride a = 7 m\n", "part.mdl")
    path = write_model('include "part.mdl"\noverride a = 2 m\n')
    with pytest.raises(errors.DimensionError) as info:
        load_model(path)
    assert str(info.value) == "part.mdl:2:14: the override 7 m of 'a' lies outside its limits [0 m, 5 m]"


@pytest.mark.parametrize(
    "part, message",
    [
        (
            "template marker() { point m = (0, 0, 1 cm) }\n",
            "parts/p.mdl:1:1: template 'marker' is declared in a file included inside a frame or template "
            "(at model.mdl:2:3): a file that declares templates is included at the top level",
        ),
        (
            "param q = 1 m\noverride q = 2 m\n",
            "parts/p.mdl:2:1: 'override' in a file included inside a frame or template (at model.mdl:2:3): "
            "a file with overrides is included at the top level",
        ),
    ],
)
def test_a_file_with_templates_or_overrides_included_inside_a_frame_names_the_include(part, message, write_model):
    """They are at the top level of their own file: 'templates are declared at the top level of a
    file' did not say what to change."""
    write_model(part, "parts/p.mdl")
    with pytest.raises(errors.MdlError) as info:
        load_model(write_model('frame f {\n  include "parts/p.mdl"\n}\n'))
    assert str(info.value).startswith(message)
    assert load_model(write_model('include "parts/p.mdl"\n')).names("param") in ([], ["q"])  # at the top: fine


def test_a_template_declared_in_a_template_is_refused_not_ignored():
    with pytest.raises(errors.MdlError, match=r"^<string>:1:16: templates are declared at the top level of a file"):
        load_model_text("template a() { template b() { point p = (0, 0, 0) } }\n")


def test_include_cycle_is_reported_with_the_chain(write_model):
    write_model('include "b.mdl"\n', "a.mdl")
    write_model('include "a.mdl"\n', "b.mdl")
    with pytest.raises(errors.IncludeError) as info:
        load_model("a.mdl")
    assert str(info.value) == "b.mdl:1:1: include cycle: a.mdl -> b.mdl -> a.mdl"


def test_missing_mesh_file_is_located(write_model):
    path = write_model('frame f {\n  shape mesh("missing.stl")\n}\n')
    with pytest.raises(errors.MeshError) as info:
        load_model(path)
    assert str(info.value).startswith("model.mdl:2:14: mesh file not found: ")


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "mesh file is empty"),
        (b"solid x\n this is not an stl file at all \x00\x01\x02", "mesh"),
    ],
)
def test_empty_or_corrupt_mesh_is_a_mesh_error(content, message, write_model, tmp_path, monkeypatch):
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    (tmp_path / "part.stl").write_bytes(content)
    path = write_model('frame f {\n  shape mesh("part.stl")\n}\n')
    for _ in range(2):  # the second time too: a mesh that failed is never kept in the cache folder
        with pytest.raises(errors.MeshError) as info:
            load_model(path)
        assert message in str(info.value)
        assert str(info.value).startswith("model.mdl:2:14: ")
    assert not list(tmp_path.glob("cache/meshes/*"))


def test_binary_include_is_an_include_error(write_model, tmp_path):
    (tmp_path / "blob.mdl").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe")
    path = write_model('include "blob.mdl"\n')
    with pytest.raises(errors.IncludeError) as info:
        load_model(path)
    assert "not UTF-8 text" in str(info.value)


def test_every_model_error_is_an_mbcal_error():
    for name in dir(errors):
        obj = getattr(errors, name)
        if isinstance(obj, type) and issubclass(obj, Warning):  # warnings have a base of their own
            assert issubclass(obj, errors.MbcalWarning), name
        elif isinstance(obj, type) and issubclass(obj, Exception):
            assert issubclass(obj, errors.MbcalError), name


def test_a_byte_order_mark_is_skipped_and_bytes_that_are_not_utf8_are_located(tmp_path):
    """A model that starts with a UTF-8 byte-order mark was 'unexpected character' at 1:1 (the CSV
    and JSON readers skip it); a Latin-1 byte was reported without its line."""
    bom = tmp_path / "bom.mdl"
    bom.write_bytes(b"\xef\xbb\xbfparam a = 1 m\n")
    assert [p.name for p in load_model(bom).params] == ["a"]
    latin = tmp_path / "latin.mdl"
    latin.write_bytes(b"param a = 1 m\n# caf\xe9\n")
    with pytest.raises(errors.IncludeError) as info:
        load_model(latin)
    assert ":2:6: not UTF-8 text (byte 20)" in str(info.value)
    latin.write_bytes("param a = 1 m\n# µµ ".encode() + b"caf\xe9\n")  # the column counts characters, not bytes
    with pytest.raises(errors.IncludeError) as info:
        load_model(latin)
    assert ":2:9: not UTF-8 text (byte 25)" in str(info.value)
    latin.write_bytes(b"param a = 1 m\r# caf\xe9\r")  # bare CR line ends: line 2 still
    with pytest.raises(errors.IncludeError) as info:
        load_model(latin)
    assert ":2:6: not UTF-8 text (byte 20)" in str(info.value)


@pytest.mark.parametrize(
    "text, where, message",
    [
        # the let first: still located at the let
        ("let x = 5 cm\nparam x = 1 m\n", "1:5", "let 'x' has the name of parameter 'x' declared at model.mdl:2:1"),
        ("frame f {\n  param x = 1 m\n  let x = 5 cm\n}\n", "3:7", "parameter 'f.x' declared at model.mdl:2:3"),
        ("param f.x = 1 m\nframe f { let x = 5 cm }\n", "2:15", "parameter 'f.x' declared at model.mdl:1:1"),
        ("param q[1..3] = 0 deg\nlet q2 = 1 deg\n", "2:5", "parameter 'q2' declared at model.mdl:1:1"),
        (
            "template t() {\n  param x = 1 m\n  let x = 5 cm\n}\nobject o = t()\n",
            "3:7",
            "let 'x' has the name of parameter 'o.x' declared at model.mdl:2:3",
        ),
        (
            "template t(w) {\n  param w = 1 m\n  point p = (w, 0, 0)\n}\nobject o = t(5 cm)\n",
            "1:12",
            "argument 'w' of template 't' has the name of parameter 'o.w' declared at model.mdl:2:3",
        ),
    ],
)
def test_a_let_or_template_argument_never_hides_a_parameter_of_its_scope(text, where, message, write_model):
    """'param x' and 'let x' in one scope: 'x' silently was the let (the parameter, in whatever order
    they were written, was used nowhere)."""
    with pytest.raises(errors.DuplicateNameError) as info:
        load_model(write_model(text))
    assert str(info.value).startswith(f"model.mdl:{where}: ")
    assert message in str(info.value)


def test_an_inner_parameter_is_found_before_an_outer_let(write_model):
    """Names are looked up scope by scope, innermost first: a frame's own parameter was hidden by a
    let of the same name at the top level; a let inside a frame still hides an outer parameter."""
    model = load_model(
        write_model(
            "let u = 5 cm\nframe f {\n  param u = 1 m\n  point p = (u, 0, 0)\n}\n"
            "param v = 1 m\nframe g {\n  let v = 2 cm\n  point p = (v, 0, 0)\n}\n"
        )
    )
    from mbcal.modeling import modeler

    scene = modeler(model, model.nominal)
    assert scene.point("f.p")[0] == pytest.approx(1.0)
    assert scene.point("g.p")[0] == pytest.approx(0.02)
    assert model.param("f.u").nominal == 1.0


def test_a_lone_surrogate_in_model_text_is_a_located_error():
    """A str with a lone surrogate (bytes decoded with errors='surrogateescape') raised a raw
    UnicodeEncodeError; its rendering shows the line with U+FFFD in its place (printable)."""
    with pytest.raises(errors.MdlSyntaxError) as info:
        load_model_text("param a = 1 m # \udc80")
    assert str(info.value) == (
        "<string>:1:17: the text holds U+DC80, a lone surrogate, which is not Unicode text "
        "(was it decoded with errors='surrogateescape'?)"
    )
    info.value.render().encode("utf-8")
