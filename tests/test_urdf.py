"""URDF in, URDF out: import as a model, forward kinematics against yourdfpy, export with offsets folded."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import trimesh
import yourdfpy

import mbcal
from mbcal.errors import MdlError
from mbcal.export.urdf import write_urdf
from mbcal.language import load_urdf
from mbcal.language.urdf import resolve_mesh, urdf_names, urdf_to_mdl
from mbcal.outputs import OutputError

from conftest import ROOT

ARM = ROOT / "tests" / "data" / "arm7.urdf"
JOINTS = [f"joint{i}" for i in range(1, 8)]
LINKS = ["base_link", *(f"link{i}" for i in range(1, 8)), "tool-center"]


@pytest.fixture(scope="module")
def arm():
    return mbcal.load_model(ARM)


def urdf_fk(path, readings: dict[str, float], links) -> dict[str, np.ndarray]:
    """yourdfpy's own forward kinematics: T_root_link for every link."""
    robot = yourdfpy.URDF.load(str(path), load_meshes=False)
    robot.update_cfg(readings)
    return {link: robot.get_transform(link, robot.base_link) for link in links}


def mbcal_fk(model, values: dict[str, float], links, names=None) -> dict[str, np.ndarray]:
    """mbcal's forward kinematics: the world pose of every link frame."""
    names = names or {}
    scene = mbcal.modeler(model, mbcal.parameter_vector(model, values))
    return {link: np.asarray(scene.frame(names.get(link, link))) for link in links}


def readings(rng, joints=JOINTS) -> dict[str, float]:
    return {j: float(rng.uniform(-2.5, 2.5)) for j in joints}


def assert_same_poses(a: dict[str, np.ndarray], b: dict[str, np.ndarray], atol=1e-9):
    assert a.keys() == b.keys()
    for link in a:
        np.testing.assert_allclose(a[link], b[link], rtol=0, atol=atol, err_msg=link)


# ---- import ---------------------------------------------------------------------------------------


def test_the_urdf_loads_as_a_model(arm):
    assert arm.path == str(ARM)
    names = set(arm.names("param"))
    for j in [*JOINTS, "tool_mount"]:
        assert {f"{j}.{f}" for f in ("x", "y", "z", "roll", "pitch", "yaw")} <= names
    for j in JOINTS:
        assert arm.param(f"{j}.q").per_configuration
        assert arm.param(f"{j}.q").unit == "deg"
        offset = arm.param(f"{j}.offset")
        assert not offset.per_configuration and offset.nominal == 0.0
        assert offset.lower == pytest.approx(-math.radians(5)) and offset.upper == pytest.approx(math.radians(5))
    assert "tool_mount.q" not in names and "tool_mount.offset" not in names  # a fixed joint
    z = arm.param("joint1.z")
    assert z.nominal == pytest.approx(0.12) and z.lower == pytest.approx(0.10) and z.upper == pytest.approx(0.14)
    assert arm.param("joint2.roll").nominal == pytest.approx(math.pi / 2, abs=1e-15)
    assert arm.param("joint2.roll").upper == pytest.approx(math.pi / 2 + math.radians(2))
    assert len(arm.frames) == 9 and arm.frames[0].name == "base_link"
    for link in LINKS:
        mdl = link.replace("-", "_")
        assert arm.resolve("frame", mdl).endswith(mdl)
        assert arm.resolve("point", f"{mdl}.origin").endswith(f"{mdl}.origin")
    joints = [f.joint for f in arm.frames if f.joint is not None]
    assert len(joints) == 7 and {j.kind for j in joints} == {"revolute"}
    assert joints[0].lower == pytest.approx(-2.9) and joints[0].upper == pytest.approx(2.9)
    kinds = sorted(s.kind for s in arm.shapes)
    assert kinds == ["box", "box", "box", "cylinder", "cylinder", "cylinder", "cylinder", "sphere", "sphere", "sphere"]
    assert set(arm.measures) == {"image_point", "point3d", "distance", "angle"}
    assert urdf_names(ARM) == {
        "link": {link: link.replace("-", "_") for link in LINKS},
        "joint": {**{j: j for j in JOINTS}, "tool-mount": "tool_mount"},
    }


def test_the_generated_text_names_the_urdf_originals():
    text = urdf_to_mdl(ARM)
    assert "link 'tool-center' -> tool_center" in text and "joint 'tool-mount' -> tool_mount" in text
    assert "link link1 at pose(joint1.x, joint1.y, joint1.z, joint1.roll, joint1.pitch, joint1.yaw)" in text
    assert "joint revolute((0, 0.6, 0.8), joint7.q, offset = joint7.offset" in text
    assert "param joint1.q = 0 deg per configuration" in text
    assert "param joint1.offset = 0 deg in [-5 deg, 5 deg]" in text
    # The text is a model of its own, beside the URDF.
    model = mbcal.load_model_text(text, str(ARM.with_suffix(".mdl")))
    assert len(model.params) == 62


def test_forward_kinematics_equals_yourdfpys(arm):
    rng = np.random.default_rng(11)
    names = {link: link.replace("-", "_") for link in LINKS}
    for _ in range(5):
        q = readings(rng)
        ours = mbcal_fk(arm, {f"{j}.q": v for j, v in q.items()}, LINKS, names)
        assert_same_poses(ours, urdf_fk(ARM, q, LINKS))


def test_a_joint_offset_adds_to_the_reading(arm):
    rng = np.random.default_rng(12)
    names = {link: link.replace("-", "_") for link in LINKS}
    offsets = {j: float(rng.uniform(-0.08, 0.08)) for j in JOINTS}
    for _ in range(3):
        q = readings(rng)
        values = {**{f"{j}.q": v for j, v in q.items()}, **{f"{j}.offset": d for j, d in offsets.items()}}
        shifted = {j: q[j] + offsets[j] for j in JOINTS}
        assert_same_poses(mbcal_fk(arm, values, LINKS, names), urdf_fk(ARM, shifted, LINKS))


# ---- export -----------------------------------------------------------------------------------------

CALIBRATED = {
    "joint2.x": 0.023,
    "joint3.y": -0.296,
    "joint4.pitch": -0.3 + 0.012,
    "joint5.yaw": -0.15 - 0.01,
    "tool_mount.z": 0.125,
    "joint1.offset": 0.031,
    "joint3.offset": -0.052,
    "joint6.offset": 0.044,
    "joint7.offset": -0.02,
}


def test_export_folds_offsets_so_readings_give_the_calibrated_kinematics(arm, tmp_path):
    before = ARM.read_bytes()
    out = tmp_path / "arm7_calibrated.urdf"
    changed = write_urdf(CALIBRATED, ARM, out)
    assert ARM.read_bytes() == before
    assert set(changed) == {"joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7", "tool-mount"}
    assert changed["joint3"]["offset"] == pytest.approx(-0.052)
    text = out.read_text(encoding="utf-8")
    assert "encoder offset -2.97938" in text and "folded in" in text and "Calibrated by mbcal" in text
    assert '<inertia ixx="0.02"' in text and '<dynamics damping="0.1"/>' in text  # the rest is kept
    rng = np.random.default_rng(13)
    names = {link: link.replace("-", "_") for link in LINKS}
    for _ in range(4):
        q = readings(rng)
        ours = mbcal_fk(arm, {**CALIBRATED, **{f"{j}.q": v for j, v in q.items()}}, LINKS, names)
        assert_same_poses(urdf_fk(out, q, LINKS), ours)
    # The written URDF loads as a model whose nominal kinematics are the calibrated ones.
    again = load_urdf(out)
    assert again.param("joint2.x").nominal == pytest.approx(0.023, abs=1e-15)
    q = readings(rng)
    assert_same_poses(
        mbcal_fk(again, {f"{j}.q": v for j, v in q.items()}, LINKS, names),
        mbcal_fk(arm, {**CALIBRATED, **{f"{j}.q": v for j, v in q.items()}}, LINKS, names),
    )


def test_export_leaves_joints_without_estimates_untouched_and_never_overwrites_its_input(tmp_path):
    out = tmp_path / "only_one.urdf"
    write_urdf({"joint4.offset": 0.01, "joint4.q": 3.0, "joint4.q@c1": 1.0, "camera.f": 600.0}, ARM, out)
    text = out.read_text(encoding="utf-8")
    assert text.count("mbcal: calibrated origin") == 1
    assert '<origin xyz="0 0 0.12" rpy="0 0 0"/>' in text  # joint1, as written
    with pytest.raises(OutputError, match="refusing to overwrite"):
        write_urdf({"joint1.offset": 0.01}, ARM, ARM)


def test_write_model_of_a_urdf_robot_writes_a_urdf_and_the_guide_says_so(arm, tmp_path):
    """docs/urdf.md's Limitations said write_model writes .mdl text ('for a robot read from a URDF
    use write_urdf'); what CalibrationResult.write_model calls writes the calibrated URDF for a
    .urdf name, and .mdl text with overrides for any other."""
    from mbcal.export.mdl import write_calibrated_model  # what CalibrationResult.write_model calls

    write_calibrated_model(arm, CALIBRATED, tmp_path / "via_model.urdf")
    write_urdf(CALIBRATED, ARM, tmp_path / "direct.urdf")
    text = (tmp_path / "via_model.urdf").read_text(encoding="utf-8")
    assert text.count("folded in") == 4 and text.startswith("<?xml")  # the four offsets
    q = readings(np.random.default_rng(3))
    assert_same_poses(urdf_fk(tmp_path / "via_model.urdf", q, LINKS), urdf_fk(tmp_path / "direct.urdf", q, LINKS))
    write_calibrated_model(arm, CALIBRATED, tmp_path / "via_model.mdl")
    again = mbcal.load_model(tmp_path / "via_model.mdl")
    assert again.param("joint3.offset").nominal == pytest.approx(CALIBRATED["joint3.offset"], abs=1e-12)
    guide = (ROOT / "docs" / "urdf.md").read_text(encoding="utf-8")
    assert "`CalibrationResult.write_model` writes `.mdl` text" not in guide
    assert "`result.write_model(path)` (and `mbcal solve --write-model PATH`) does the same" in guide


# ---- a calibration through the library ------------------------------------------------------------


@pytest.mark.slow
def test_offsets_and_origin_errors_are_recovered_from_3d_points(arm, tmp_path):
    rng = np.random.default_rng(21)
    configurations = {f"c{k}": {f"{j}.q": float(rng.uniform(-1.5, 1.5)) for j in JOINTS} for k in range(6)}
    records = [
        {"kind": "point3d", "config": c, "point": f"{link.replace('-', '_')}.origin", "sigma": 0.5e-3}
        for c in configurations
        for link in LINKS[1:]
    ]
    plan = mbcal.measurements_from_records(records, arm, configurations=configurations)
    truth = {f"{j}.offset": math.radians(float(rng.uniform(-4, 4))) for j in JOINTS}
    truth["joint3.y"] = -0.3 + 0.006
    truth["joint5.z"] = 0.06 - 0.004
    data = mbcal.simulate(arm, plan, truth, noise=1.0, seed=4)
    result = mbcal.calibrate(arm, data, ["joint*.offset", "joint3.y", "joint5.z"], restarts=4, seed=0, points=[])
    assert result.ok
    for name, value in truth.items():
        assert abs(result.values[name] - value) < 3 * result.std[name], name
    assert max(result.std[f"{j}.offset"] for j in JOINTS) < math.radians(0.5)
    # The result exports: the calibrated URDF reproduces the calibrated model at the readings.
    out = tmp_path / "calibrated.urdf"
    write_urdf(result, ARM, out)
    names = {link: link.replace("-", "_") for link in LINKS}
    q = configurations["c3"]
    ours = mbcal_fk(arm, {**result.values, **q}, LINKS, names)
    assert_same_poses(urdf_fk(out, {k.split(".")[0]: v for k, v in q.items()}, LINKS), ours)
    # Through the result (what 'mbcal solve --write-model' does): a URDF, or .mdl text with overrides.
    via_result = tmp_path / "via_result.urdf"
    result.write_model(via_result)
    assert_same_poses(urdf_fk(via_result, {k.split(".")[0]: v for k, v in q.items()}, LINKS), ours)
    as_mdl = tmp_path / "calibrated.mdl"
    result.write_model(as_mdl)
    again = mbcal.load_model(as_mdl)
    for name, value in result.values.items():
        assert again.param(name).nominal == pytest.approx(value, rel=1e-9, abs=1e-12), name


# ---- other joint kinds, names, meshes -------------------------------------------------------------

SMALL = """<?xml version="1.0"?>
<robot name="small">
  <link name="base">
    <visual name="dot"><geometry><sphere radius="0"/></geometry></visual>
  </link>
  <link name="slide">
    <visual><geometry><mesh filename="package://small_pkg/meshes/part.stl" scale="0.5 0.5 2"/></geometry></visual>
    <visual><geometry><mesh filename="meshes/missing.stl"/></geometry></visual>
  </link>
  <link name="wheel"/>
  <link name="2nd link"/>
  <link name="finger"/>
  <joint name="joint" type="prismatic">
    <parent link="base"/><child link="slide"/>
    <origin xyz="0.1 0 0.2" rpy="0 0.3 0"/>
    <axis xyz="1 0 0"/>
    <limit lower="-0.1" upper="0.3" effort="10" velocity="1"/>
  </joint>
  <joint name="spin" type="continuous">
    <parent link="slide"/><child link="wheel"/>
    <origin xyz="0 0.05 0"/>
  </joint>
  <joint name="link" type="revolute">
    <parent link="wheel"/><child link="2nd link"/>
    <origin xyz="0.1 0 0" rpy="0 0 0.7"/>
    <axis xyz="0 1 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/>
  </joint>
  <joint name="follow" type="prismatic">
    <parent link="slide"/><child link="finger"/>
    <origin xyz="0 -0.02 0.03" rpy="0.2 0 0"/>
    <axis xyz="0 0 1"/>
    <limit lower="0" upper="0.04" effort="10" velocity="1"/>
    <mimic joint="link" multiplier="0.02" offset="0.01"/>
  </joint>
</robot>
"""
SMALL_LINKS = ["base", "slide", "wheel", "2nd link", "finger"]
SMALL_NAMES = {"2nd link": "_2nd_link"}


@pytest.fixture
def small(tmp_path):
    folder = tmp_path / "small_pkg"
    (folder / "urdf").mkdir(parents=True)
    (folder / "meshes").mkdir()
    trimesh.creation.box(extents=(0.1, 0.2, 0.05)).export(folder / "meshes" / "part.stl")
    path = folder / "urdf" / "small.urdf"
    path.write_text(SMALL, encoding="utf-8")
    return path


def test_the_urdf_is_read_once_and_the_model_is_of_the_bytes_its_key_names(tmp_path, monkeypatch):
    """lxml and yourdfpy each read the file: saved in between, the model came from the new text
    and its key (Model.file_digests) from the old one, so a program of one was filed as the other."""
    import hashlib

    from mbcal.language import files

    path = tmp_path / "arm7.urdf"
    original = ARM.read_bytes()
    path.write_bytes(original)
    read = files.read_bytes

    def read_then_save(p):
        data = read(p)
        path.write_bytes(original.replace(b'<origin xyz="0 0 0.12"', b'<origin xyz="0 0 0.52"'))
        return data

    monkeypatch.setattr(files, "read_bytes", read_then_save)
    model = load_urdf(path)
    assert hashlib.sha256(original).hexdigest() in dict(model.file_digests).values()
    q = readings(np.random.default_rng(8))
    values = {f"{j}.q": v for j, v in q.items()}
    names = {link: link.replace("-", "_") for link in LINKS}
    assert_same_poses(mbcal_fk(model, values, LINKS, names), urdf_fk(ARM, q, LINKS))  # the text as first read


def test_prismatic_continuous_and_mimic_joints_and_renamed_names(small):
    model = load_urdf(small)
    assert urdf_names(small)["joint"] == {"joint": "joint_", "spin": "spin", "link": "link_", "follow": "follow"}
    assert model.param("joint_.q").unit == "m" and model.param("joint_.offset").upper == pytest.approx(0.005)
    assert model.param("spin.q").unit == "deg"
    assert not model.has("param", "follow.q") and model.has("param", "follow.offset")  # mimic: no reading
    rng = np.random.default_rng(5)
    for _ in range(3):
        q = {
            "joint": float(rng.uniform(-0.1, 0.3)),
            "spin": float(rng.uniform(-4, 4)),
            "link": float(rng.uniform(-1, 1)),
        }
        values = {f"{urdf_names(small)['joint'][j]}.q": v for j, v in q.items()}
        assert_same_poses(mbcal_fk(model, values, SMALL_LINKS, SMALL_NAMES), urdf_fk(small, q, SMALL_LINKS))
    # Offsets of every kind fold into the exported origins.
    calibrated = {"joint_.offset": 0.004, "spin.offset": 0.2, "link_.offset": -0.05, "follow.offset": 0.003}
    out = small.parent / "small_calibrated.urdf"
    write_urdf(calibrated, small, out)
    q = {"joint": 0.12, "spin": 1.0, "link": 0.4}
    values = {**calibrated, **{f"{urdf_names(small)['joint'][j]}.q": v for j, v in q.items()}}
    assert_same_poses(urdf_fk(out, q, SMALL_LINKS), mbcal_fk(model, values, SMALL_LINKS, SMALL_NAMES))


def test_meshes_resolve_through_package_names_and_missing_ones_become_comments(small, tmp_path):
    part = (tmp_path / "small_pkg" / "meshes" / "part.stl").resolve()
    assert resolve_mesh("package://small_pkg/meshes/part.stl", small) == part
    assert resolve_mesh("../meshes/part.stl", small) == part
    assert resolve_mesh(f"file://{part}", small) == part
    assert resolve_mesh("package://other_pkg/meshes/part.stl", small) is None
    text = urdf_to_mdl(small)
    assert 'mesh("../meshes/part.stl", scale = (0.5, 0.5, 2))' in text
    assert "mesh file not found, left out: meshes/missing.stl" in text
    assert "visual 0 'dot': a sphere with an invalid size (not positive), left out" in text
    model = load_urdf(small)
    (mesh,) = [s for s in model.shapes if s.kind == "mesh"]
    assert mesh.mesh.vertices.shape[1] == 3
    scene = mbcal.modeler(model, model.nominal)
    assert np.asarray(scene.shape_dims)[model.shapes.index(mesh)] == pytest.approx([0.5, 0.5, 2])
    # A relative mesh name is rewritten when the calibrated URDF goes to another folder.
    small.write_text(SMALL.replace("package://small_pkg/meshes/part.stl", "../meshes/part.stl"), encoding="utf-8")
    out = tmp_path / "elsewhere.urdf"
    write_urdf({}, small, out)
    assert 'filename="small_pkg/meshes/part.stl"' in out.read_text(encoding="utf-8")


# ---- errors ------------------------------------------------------------------------------------------


def write(tmp_path, text: str, name: str = "bad.urdf"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_malformed_xml_names_the_file_and_line(tmp_path):
    path = write(tmp_path, '<?xml version="1.0"?>\n<robot name="r">\n  <link name="a">\n</robot>\n')
    with pytest.raises(MdlError, match=r"bad\.urdf:4:\d+: malformed XML"):
        mbcal.load_model(path)


def test_a_joint_with_a_missing_link_is_an_error_at_its_line(tmp_path):
    path = write(
        tmp_path,
        '<robot name="r">\n  <link name="a"/>\n'
        '  <joint name="j" type="fixed">\n    <parent link="a"/>\n    <child link="b"/>\n  </joint>\n</robot>\n',
    )
    with pytest.raises(MdlError, match=r"bad\.urdf:3:3: joint 'j' refers to a missing child link 'b'"):
        mbcal.load_model(path)


@pytest.mark.parametrize(
    "body, message",
    [
        ('<joint name="free" type="floating"><parent link="a"/><child link="b"/></joint>', "joint 'free' is floating"),
        ('<joint name="j" type="fixed"><child link="b"/></joint>', "not a valid URDF"),
        ('<link name="c"/><joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint>', "a, c"),
        (
            '<joint name="j" type="fixed"><parent link="a"/><child link="b"/></joint>'
            '<joint name="k" type="fixed"><parent link="b"/><child link="a"/></joint>',
            "cycle",
        ),
        ('<joint name="j" type="ball"><parent link="a"/><child link="b"/></joint>', "unknown type 'ball'"),
    ],
)
def test_urdfs_mbcal_cannot_model_are_refused_with_the_file_name(tmp_path, body, message):
    path = write(tmp_path, f'<robot name="r"><link name="a"/><link name="b"/>{body}</robot>')
    with pytest.raises(MdlError, match="bad.urdf") as err:
        urdf_to_mdl(path)
    assert message in str(err.value)


def test_a_cycle_or_a_second_root_is_an_error_at_a_line_of_it(tmp_path):
    """The cycle's message named the file only, though the docs promise the joint's line."""
    links = '<robot name="r">\n  <link name="a"/>\n  <link name="b"/>\n'
    cycle = (
        '  <joint name="ab" type="fixed">\n    <parent link="a"/>\n    <child link="b"/>\n  </joint>\n'
        '  <joint name="ba" type="fixed">\n    <parent link="b"/>\n    <child link="a"/>\n  </joint>\n</robot>\n'
    )
    with pytest.raises(
        MdlError, match=r"bad\.urdf:8:3: the links do not form one tree: the joints 'ba', 'ab' form a cycle"
    ):
        mbcal.load_model(write(tmp_path, links + cycle))
    with pytest.raises(MdlError, match=r"bad\.urdf:3:3: the links do not form one tree: several root links: a, b"):
        mbcal.load_model(write(tmp_path, links + "</robot>\n"))


def test_a_revolute_or_prismatic_joint_without_limit_is_an_error_at_its_line(tmp_path):
    """URDF requires <limit> for both (urdfdom refuses the file); the joint was read as unlimited,
    and inverse kinematics turned it anywhere."""
    joint = '  <joint name="j" type="{}">\n    <parent link="a"/>\n    <child link="b"/>\n{}  </joint>\n</robot>\n'
    links = '<robot name="r">\n  <link name="a"/>\n  <link name="b"/>\n'
    limit = '    <limit lower="-1" upper="1" effort="1" velocity="1"/>\n'
    for kind in ("revolute", "prismatic"):
        with pytest.raises(MdlError, match=rf"bad\.urdf:4:3: joint 'j' is {kind} but has no <limit>") as err:
            mbcal.load_model(write(tmp_path, links + joint.format(kind, "")))
        assert "add <limit" in str(err.value) and ("continuous" in str(err.value)) == (kind == "revolute")
        assert mbcal.load_model(write(tmp_path, links + joint.format(kind, limit))) is not None
    assert mbcal.load_model(write(tmp_path, links + joint.format("continuous", ""))) is not None


def test_a_mimic_of_a_joint_that_does_not_exist_says_so_at_the_mimic(tmp_path):
    """It said 'which is not a moving joint without <mimic>', at the joint's line."""
    text = SMALL.replace('<mimic joint="link"', '<mimic joint="lnik"')
    path = write(tmp_path, text)
    with pytest.raises(MdlError) as err:
        mbcal.load_model(path)
    line = next(k for k, row in enumerate(text.splitlines(), 1) if "<mimic" in row)
    assert str(err.value).startswith(f"{path}:{line}:5: joint 'follow' mimics 'lnik', which does not exist")
    assert "did you mean 'link'?" in str(err.value)
    # one that exists but cannot be followed: why, at the <mimic> too
    with pytest.raises(MdlError, match=rf"{line}:5: joint 'follow' mimics 'spin', which mimics 'link' itself"):
        mbcal.load_model(
            write(tmp_path, SMALL.replace('<mimic joint="link"', '<mimic joint="spin"').replace(
                '<origin xyz="0 0.05 0"/>', '<origin xyz="0 0.05 0"/><mimic joint="link"/>'
            ))
        )  # fmt: skip


def test_mbcal_check_reads_a_urdf():
    done = subprocess.run(
        [sys.executable, "-m", "mbcal", "check", str(ARM)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "joint7.offset" in done.stdout and "ok: 1 model checked" in done.stdout


def test_mbcal_check_reports_a_bad_urdf_without_a_traceback(tmp_path):
    path = write(tmp_path, '<robot name="r"><link name="a"/>')
    done = subprocess.run(
        [sys.executable, "-m", "mbcal", "check", str(path)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 2
    assert "bad.urdf:1:" in done.stderr and "Traceback" not in done.stderr


def test_a_value_the_urdf_reader_cannot_take_is_located_at_its_attribute(tmp_path):
    text = ARM.read_text()
    start = text.index('xyz="') + len('xyz="')
    words = text[start : text.index('"', start)].split()
    bad = text[:start] + " ".join([words[0], "abc", *words[2:]]) + text[start + len(" ".join(words)) :]
    path = tmp_path / "bad.urdf"
    path.write_text(bad)
    line = bad[:start].count("\n") + 1
    column = start - bad.rfind("\n", 0, start) + len(words[0]) + 1
    with pytest.raises(MdlError) as info:
        mbcal.load_model(path)
    assert "could not convert string to float: 'abc'" in info.value.message
    assert (info.value.span.line, info.value.span.column) == (line, column)
    assert bad.splitlines()[line - 1][column - 1 : column + 2] == "abc"


@pytest.mark.parametrize(
    "change, where, message",
    [
        (('xyz="0 0 0"', 'xyz="nan 0 0"'), "8:5", "its <origin> is not finite numbers"),
        (('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>'), "9:5", "its <axis> must be a finite, non-zero vector"),
        (('lower="-1" upper="1"', 'lower="1" upper="-1"'), "10:5", "its <limit> must have lower ≤ upper"),
        # the joint on one line: the column finds the element
        (('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>'), "5:", "its <axis> must"),
    ],
)
def test_a_joints_bad_numbers_are_errors_at_the_elements_line(tmp_path, change, where, message):
    """They were errors at a line of the .mdl written from the URDF ('robot.urdf.mdl:6:17: unexpected
    'm''), a file the user never had; then at the joint's line, column 1: now at the <origin>,
    <axis> or <limit> element."""
    text = (
        '<?xml version="1.0"?>\n<robot name="r">\n  <link name="base"/>\n  <link name="a"/>\n'
        '  <joint name="j" type="revolute">\n    <parent link="base"/>\n    <child link="a"/>\n'
        '    <origin xyz="0 0 0" rpy="0 0 0"/>\n    <axis xyz="0 0 1"/>\n'
        '    <limit lower="-1" upper="1" effort="1" velocity="1"/>\n  </joint>\n</robot>\n'
    )
    path = tmp_path / "robot.urdf"
    text = text.replace(*change)
    if where == "5:":  # the whole joint on its first line
        text = text.replace("\n    ", "")
        where += str(text.splitlines()[4].index("<axis") + 1)
    path.write_text(text)
    with pytest.raises(mbcal.MbcalError) as info:
        mbcal.load_model(path)
    assert str(info.value).startswith(f"{path}:{where}: joint 'j': {message}"), str(info.value)
    line, column = map(int, where.split(":"))
    assert text.splitlines()[line - 1][column - 1 :].startswith("<" + message.split("<")[1].split(">")[0])


def test_a_start_tag_split_over_lines_is_located_at_its_opening(tmp_path):
    """lxml gives the line where a start tag ends: a '<joint' written over three lines was
    reported at its 'type=' line, column 1."""
    path = tmp_path / "robot.urdf"
    path.write_text(
        '<robot name="r">\n<link name="base"/>\n<link name="l1"/>\n<joint\n   name="j1"\n   type="revolute">\n'
        '  <parent link="base"/>\n  <child link="l1"/>\n  <axis\n     xyz="0 0 0"/>\n'
        '  <limit lower="0" upper="1" effort="1" velocity="1"/>\n</joint>\n</robot>\n'
    )
    with pytest.raises(mbcal.MbcalError) as info:
        mbcal.load_model(path)
    assert str(info.value).startswith(f"{path}:9:3: joint 'j1': its <axis> must be"), str(info.value)
    path.write_text(path.read_text().replace('<child link="l1"/>', '<child link="l2"/>'))
    with pytest.raises(mbcal.MbcalError) as info:
        mbcal.load_model(path)
    assert str(info.value).startswith(f"{path}:4:1: joint 'j1' refers to a missing child link 'l2'"), str(info.value)


def test_a_limit_without_lower_or_upper_takes_urdfs_default_of_zero(tmp_path):
    """URDF's lower and upper default to 0 (urdfdom reads them so); a missing side was read as no
    limit, so inverse kinematics could turn the joint where the robot cannot."""
    from mbcal.kinematics import Kinematics

    joint = (
        '  <joint name="j" type="revolute">\n    <parent link="a"/>\n    <child link="b"/>\n'
        '    <axis xyz="0 0 1"/>\n    <limit {} effort="1" velocity="1"/>\n  </joint>\n'
    )
    tip = (
        '  <joint name="t" type="fixed">\n    <parent link="b"/>\n    <child link="c"/>\n'
        '    <origin xyz="1 0 0"/>\n  </joint>\n'
    )
    links = '<robot name="r">\n  <link name="a"/>\n  <link name="b"/>\n  <link name="c"/>\n'
    for attributes, low, high in (('upper="1"', 0.0, 1.0), ('lower="-1"', -1.0, 0.0), ("", 0.0, 0.0)):
        path = write(tmp_path, links + joint.format(attributes) + tip + "</robot>\n")
        text = urdf_to_mdl(path)
        assert "<limit> has no" in text and ("cannot move" in text) == (low == high)
        kin = Kinematics(mbcal.load_model(path), "c.origin")
        assert (kin.lower[0], kin.upper[0]) == pytest.approx((low, high))
    # an upper below the defaulted lower is the same error as one written out
    with pytest.raises(MdlError, match=r"must have lower ≤ upper, got lower=0 upper=-1"):
        mbcal.load_model(write(tmp_path, links + joint.format('upper="-1"') + tip + "</robot>\n"))
