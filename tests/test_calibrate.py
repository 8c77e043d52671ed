"""Calibration end to end through the library API: simulated measurements → estimates within 3σ."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

import mbcal
from mbcal.errors import OutputError, SolverError
from mbcal.export.mdl import write_calibrated_model
from mbcal.modeling import modeler
from mbcal.problem import Problem

from conftest import MEASUREMENTS, MODELS, ROOM_TRUTH


@pytest.fixture(scope="module")
def arm():
    return mbcal.load_model(MODELS / "arm7.mdl")


@pytest.fixture(scope="module")
def room_data(room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    return mbcal.simulate(room, plan, ROOM_TRUTH, noise=1.0, seed=11)


@pytest.fixture(scope="module")
def room_result(room, room_data):
    return mbcal.calibrate(room, room_data, ["room.*"], restarts=16, seed=0)


def assert_within_3_sigma(result, truth):
    for name, true in truth.items():
        err = result.values[name] - true
        assert abs(err) <= 3 * result.std[name], f"{name}: error {err:.3g}, σ {result.std[name]:.3g}"


@pytest.mark.slow
def test_room_pose_is_recovered_from_24_stereo_points(room_result):
    assert room_result.ok
    assert room_result.observability.rank == 6
    assert_within_3_sigma(room_result, ROOM_TRUTH)
    assert 0.5 < room_result.reduced_chi2 < 1.6  # the σ of 1 px is right
    assert room_result.rms["image_point"] < 2.0


def test_stereo_depth_is_the_least_certain_direction(room_result):
    lever = [p for p in room_result.points if p.point.endswith("lever.tip")]
    assert lever and all(p.parallel > p.perpendicular for p in lever)


@pytest.mark.slow
def test_arm_joint_offsets_are_recovered_over_ten_attitudes(arm):
    plan = mbcal.read_measurements(MEASUREMENTS / "arm_plan.json", arm)
    rng = np.random.default_rng(7)
    truth = {f"arm.offset{i}": math.radians(rng.uniform(-6, 6)) for i in range(1, 8)}
    data = mbcal.simulate(arm, plan, truth, noise=1.0, seed=3)
    result = mbcal.calibrate(arm, data, ["arm.offset*"], restarts=16, seed=1)
    assert result.ok and len(result.residuals) == 84
    assert_within_3_sigma(result, truth)


@pytest.mark.slow
def test_lever_angle_is_recovered_from_its_points(room):
    plan = mbcal.measurements_from_records(
        [
            {"kind": "image_point", "camera": cam, "point": f"lever.{p}", "sigma": 0.5}
            for cam in ("eyes.left", "eyes.right")
            for p in ("tip", "knob_front", "middle")
        ],
        room,
    )
    truth = {"lever.angle": math.radians(33.0)}
    data = mbcal.simulate(room, plan, truth, seed=5)
    result = mbcal.calibrate(room, data, ["lever.angle"], restarts=8)
    assert_within_3_sigma(result, truth)
    assert result.std["lever.angle"] < math.radians(0.5)


INTRINSICS_MODEL = """
param cam.fx = 800 in [700, 900]
param cam.fy = 800 in [700, 900]
param cam.cx = 320 in [280, 360]
param cam.cy = 240 in [200, 280]
param cam.k1 = 0 in [-0.3, 0.3]
param board.yaw = 0 deg per configuration
param board.tilt = 0 deg per configuration
camera cam(width = 640, height = 480, fx = cam.fx, fy = cam.fy, cx = cam.cx, cy = cam.cy, k1 = cam.k1)
frame stand at (0, 0, 1 m) * rot_y(board.yaw) * rot_x(board.tilt) {
  target board = grid(rows = 7, cols = 9, dx = 5 cm) at (-20 cm, -15 cm, 0)
}
"""


def test_camera_intrinsics_are_recovered_from_a_target_in_known_poses():
    model = mbcal.load_model_text(INTRINSICS_MODEL)
    poses = {"v1": (0, 0), "v2": (25, 0), "v3": (-25, 10), "v4": (0, -30), "v5": (15, 25)}
    configurations = {v: {"board.yaw": f"{a} deg", "board.tilt": f"{b} deg"} for v, (a, b) in poses.items()}
    records = [
        {"kind": "image_point", "config": v, "camera": "cam", "point": p.name, "sigma": 0.3}
        for v in poses
        for p in model.points
    ]
    plan = mbcal.measurements_from_records(records, model, configurations=configurations)
    truth = {"cam.fx": 812.0, "cam.fy": 806.0, "cam.cx": 331.0, "cam.cy": 236.0, "cam.k1": -0.12}
    data = mbcal.simulate(model, plan, truth, seed=9)
    result = mbcal.calibrate(model, data, ["cam.*"], restarts=8)
    assert result.ok
    assert_within_3_sigma(result, truth)


@pytest.mark.slow
def test_an_unobservable_combination_is_named_in_the_users_terms(room, room_data):
    result = mbcal.calibrate(room, room_data, ["room.x", "robot.x", "room.y", "room.z"], restarts=4)
    obs = result.observability
    assert not obs.observable and obs.rank == 3
    (combo,) = obs.unobservable
    assert set(combo.names) == {"room.x", "robot.x"}
    assert combo.coefficients["room.x"] == pytest.approx(combo.coefficients["robot.x"])
    text = combo.describe()
    assert "room.x" in text and "robot.x" in text and "cannot be determined" in text
    # Rank-deficient covariance: no crash, σ = ∞ exactly where unobservable, finite elsewhere.
    assert math.isinf(result.std["room.x"]) and math.isinf(result.std["robot.x"])
    assert math.isfinite(result.std["room.y"]) and math.isfinite(result.std["room.z"])
    assert not result.ok
    report = json.dumps(result.to_json(), allow_nan=False)  # no NaN or ∞ in the JSON report
    assert "unobservable" in report
    assert "cannot be determined" in result.summary()


@pytest.mark.slow
def test_a_parameter_no_measurement_depends_on_is_reported_alone(room, room_data):
    no_fan = room_data.subset(["fan" not in m.refs["point"] for m in room_data])
    result = mbcal.calibrate(room, no_fan, ["room.x", "fan.angle"], restarts=2)
    (combo,) = result.observability.unobservable
    assert combo.names == ["fan.angle"]
    assert combo.describe() == "'fan.angle' cannot be determined: no measurement changes when it changes"
    assert math.isinf(result.std["fan.angle"]) and math.isfinite(result.std["room.x"])


@pytest.mark.slow
def test_suggestions_rank_measurements_that_raise_the_rank(room):
    plan = mbcal.measurements_from_records(
        [{"kind": "image_point", "camera": "eyes.left", "point": p, "sigma": 1} for p in ("lever.hub", "lever.tip")],
        room,
    )
    analysis = mbcal.observe(room, plan, ["room.*"])
    obs = analysis.observability
    assert obs.rank == 4 and len(obs.unobservable) == 2
    assert obs.suggestions and obs.suggestions[0].rank_gain >= 1
    assert "image_point" in obs.suggestions[0].text


@pytest.mark.slow
def test_priors_determine_what_the_measurements_cannot(room, room_data):
    text = (MODELS / "teleexistence.mdl").read_text().replace("param robot.x   = 0 m", "param robot.x = 0 m sigma 5 mm")
    model = mbcal.load_model_text(text, str(MODELS / "prior_copy.mdl"))
    result = mbcal.calibrate(model, room_data, ["room.x", "robot.x"], restarts=2)
    assert not result.observability.observable
    assert result.observability.observable_with_priors
    assert math.isfinite(result.std["room.x"])


def test_autodiff_jacobian_matches_finite_differences(arm):
    plan = mbcal.read_measurements(MEASUREMENTS / "arm_plan.json", arm)
    data = mbcal.simulate(arm, plan, {"arm.offset2": 0.05}, seed=1)
    problem = Problem(arm, data, ["arm.offset*", "torso.q@pose03"])
    x = problem.params.x0 + np.random.default_rng(0).normal(0, 0.03, problem.params.size)
    J = problem.jacobian(x)
    h = 1e-6
    fd = np.stack(
        [(problem.residual(x + h * e) - problem.residual(x - h * e)) / (2 * h) for e in np.eye(len(x))], axis=1
    )
    np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-4)


@pytest.mark.slow
def test_calibration_is_reproducible_for_a_seed(room, room_data):
    a = mbcal.calibrate(room, room_data, ["room.*"], restarts=6, seed=42)
    b = mbcal.calibrate(room, room_data, ["room.*"], restarts=6, seed=42)
    assert a.x.tobytes() == b.x.tobytes()
    np.testing.assert_array_equal(a.solver.x0, b.solver.x0)


def test_simulate_without_noise_reproduces_the_model(room):
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", room)
    data = mbcal.simulate(room, plan, ROOM_TRUTH, noise=0.0)
    params = Problem(room, data, list(ROOM_TRUTH)).params
    # Each simulated click against the camera's own projection of the point in the true scene,
    # modeler(D, X) directly: simulate goes through the measurement models and their batching.
    scene = modeler(room, params.X(params.from_dict(ROOM_TRUTH))[0])
    for m in data:
        expected = np.asarray(scene.camera(m.refs["camera"]).project(scene.point(m.refs["point"])))
        np.testing.assert_allclose(m.value, expected, rtol=0, atol=1e-9, err_msg=m.id)
    assert len(data) == 48


def test_simulate_refuses_points_behind_the_camera(room):
    plan = mbcal.measurements_from_records([{"kind": "image_point", "camera": "eyes.left", "point": "lever.tip"}], room)
    with pytest.raises(SolverError, match="cannot be made"):
        mbcal.simulate(room, plan, {"robot.yaw": math.pi})


def test_calibrated_model_is_written_without_touching_the_input(room, room_result, tmp_path):
    source = (MODELS / "teleexistence.mdl").read_bytes()
    out = tmp_path / "calibrated.mdl"
    room_result.write_model(out)
    assert (MODELS / "teleexistence.mdl").read_bytes() == source
    again = mbcal.load_model(out)
    for name, value in room_result.values.items():
        assert again.param(name).nominal == pytest.approx(value, rel=1e-9, abs=1e-12)
    assert "param room.yaw" in out.read_text() and "override" not in out.read_text()


def test_a_model_from_text_is_written_from_its_text_and_a_file_changed_since_is_refused(room_data, tmp_path):
    """write_model re-read the file at model.path and put the estimates at the places parsed from
    the text: a comment line added to the text moved room.x's estimate onto room.y's line, with
    nothing said; a file saved after loading did the same."""
    text = "# a local copy, one comment line added\n" + (MODELS / "teleexistence.mdl").read_text()
    text = text.replace("param room.x     = 0 m   in [-10 cm, 10 cm]", "param room.x = 0 m in [-10 cm, 10 cm] bounded")
    assert "bounded" in text
    model = mbcal.load_model_text(text, str(MODELS / "teleexistence.mdl"))
    result = mbcal.calibrate(model, room_data, ["room.x", "room.y"], restarts=2)
    out = tmp_path / "from_text.mdl"
    result.write_model(out)
    again = mbcal.load_model(out)
    for name, value in result.values.items():
        assert again.param(name).nominal == pytest.approx(value, rel=1e-9, abs=1e-12), name
    assert again.param("room.z").nominal == 0.0 and "bounded" in out.read_text()
    # a model read from a file that is saved again before the write: refused, nothing written
    shutil.copytree(MODELS, tmp_path / "models")
    copy = tmp_path / "models" / "teleexistence.mdl"
    read = mbcal.load_model(copy)
    result = mbcal.calibrate(read, room_data, ["room.x"], restarts=2)
    copy.write_text("# edited\n" + copy.read_text())
    with pytest.raises(OutputError, match="has changed since the model was read"):
        result.write_model(tmp_path / "late.mdl")
    assert not (tmp_path / "late.mdl").exists()


@pytest.mark.slow
def test_values_declared_by_an_index_range_are_written_as_overrides(arm, tmp_path):
    plan = mbcal.read_measurements(MEASUREMENTS / "arm_plan.json", arm)
    data = mbcal.simulate(arm, plan, {"arm.offset3": 0.04}, seed=2)
    result = mbcal.calibrate(arm, data, ["arm.offset*"], restarts=2)
    out = tmp_path / "arm_calibrated.mdl"
    result.write_model(out)  # its include of parts/stereo.mdl is rewritten to stay valid from tmp_path
    text = out.read_text()
    assert "override arm.offset3 =" in text
    again = mbcal.load_model(out)
    assert again.param("arm.offset3").nominal == pytest.approx(result.values["arm.offset3"], rel=1e-9)


@pytest.mark.parametrize("where", ["included", "main"])
def test_a_parameter_overridden_in_an_included_file_or_the_main_one_is_written_so_the_model_loads(where, tmp_path):
    """--write-model appended 'override lever.angle = ...' to a model whose included calibration
    file already overrode it: the written model did not load ('already overridden')."""
    (tmp_path / "robot_cal.mdl").write_text(
        "param lever.angle = 20 deg in [-90 deg, 90 deg] sigma 5 deg\n"
        "param lever.length = 25 cm\n" + ("override lever.angle = 22 deg sigma 2 deg\n" if where == "included" else "")
    )
    site = tmp_path / "site.mdl"
    site.write_text(
        'include "robot_cal.mdl"\n'
        + ("override lever.angle = 22 deg sigma 2 deg\n" if where == "main" else "")
        + "object lever at (0, 0.8 m, 1.1 m) {\n  joint revolute(-y, lever.angle)\n"
        "  point tip = (0, 0, lever.length)\n}\n"
    )
    model = mbcal.load_model(site)
    out = tmp_path / "site_cal.mdl"
    write_calibrated_model(model, {"lever.angle": math.radians(29.5)}, out)
    again = mbcal.load_model(out)
    assert again.param("lever.angle").nominal == pytest.approx(math.radians(29.5), rel=1e-12)
    assert again.param("lever.angle").sigma == pytest.approx(math.radians(2), rel=1e-12)  # the model's prior kept
    assert out.read_text().count("override lever.angle") == 1  # in place when the main file has it


def test_every_relative_file_name_is_rewritten_when_the_model_is_written_to_another_folder(tmp_path):
    """A points("pts.txt") target kept its path in a model written elsewhere: the written model
    did not load ('point file not found: .../out/pts.txt')."""
    import trimesh

    for folder in ("parts", "meshes", "data", "models", "out/deeper"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "parts" / "peg.mdl").write_text("template peg() { shape cylinder(5 mm, 3 cm) }\n")
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "meshes" / "block.stl")
    (tmp_path / "data" / "pts.txt").write_text("0 0\n0.1 0\n0 0.1\n")
    source = tmp_path / "models" / "cell.mdl"
    source.write_text(
        'include "../parts/peg.mdl"\n'
        "param b.x = 0 m\n"
        'template block() { shape mesh(file = "../meshes/block.stl", scale = 0.5) }\n'
        'object a = block() at (1 m, 0, 0) { shape mesh("../meshes/block.stl") }\n'
        "object p = peg()\n"
        'frame holder { target board = points("../data/pts.txt", scale = 1 m) at (b.x, 0, 1 m) }\n'
    )
    model = mbcal.load_model(source)
    out = tmp_path / "out" / "deeper" / "cell_cal.mdl"
    write_calibrated_model(model, {"b.x": 0.01}, out)
    again = mbcal.load_model(out)
    assert again.param("b.x").nominal == pytest.approx(0.01)
    assert [Path(f).resolve() for f in again.files[1:]] == [Path(f).resolve() for f in model.files[1:]]
    assert [Path(f).resolve() for f in again.data_files] == [Path(f).resolve() for f in model.data_files]
    assert again.names("point") == model.names("point") and [s.kind for s in again.shapes] == [
        "mesh",
        "mesh",
        "cylinder",
    ]
    with pytest.raises(OutputError, match="refusing to overwrite the input file"):
        write_calibrated_model(model, {"b.x": 0.01}, tmp_path / "data" / "pts.txt")  # a file the model reads


def test_a_model_the_estimate_makes_invalid_is_not_written(tmp_path):
    """A search range that includes f < 0 let a fit find a mirror camera; the model written from
    it ('param cam.f = -685.147') was refused by mbcal check: 'fx must be positive'."""
    source = tmp_path / "cam.mdl"
    source.write_text(
        "param cam.f = 600 in [-1000, 1000]\nparam box.size = 1 m in [-1 m, 2 m]\n"
        "param box.x = 0 m limits [-1 m, 1 m]\n"
        "camera eye(width = 640, height = 480, f = cam.f)\nshape box(box.size, 1 m, 1 m) at (box.x, 0, 5 m)\n"
    )
    model = mbcal.load_model(source)
    out = tmp_path / "cam_cal.mdl"
    for values, message in (
        ({"cam.f": -685.147, "box.x": 0.1}, "camera 'eye': fx must be positive, got -685.147 with the estimated "
         "values (the estimate cam.f = -685.147)"),
        ({"box.size": -0.5}, "must be positive, got -0.5 m with the estimated values (the estimate box.size = -0.5 m)"),
        ({"box.x": 1.5}, "the estimate 1.5 m is outside the hard limits of box.x [-1, 1] m"),
    ):  # fmt: skip
        with pytest.raises(OutputError) as info:
            write_calibrated_model(model, values, out)
        assert str(info.value).startswith(f"{source}:") and f"not writing {out}: " in str(info.value)
        assert message in str(info.value)
        assert not out.exists()
    write_calibrated_model(model, {"cam.f": 685.147, "box.size": 0.5}, out)
    assert mbcal.load_model(out).param("cam.f").nominal == pytest.approx(685.147)


def test_nothing_to_estimate_is_a_clear_error(room, room_data):
    with pytest.raises(SolverError, match="nothing to estimate"):
        mbcal.calibrate(room, room_data, [])


@pytest.mark.slow
def test_range_measurements_recover_the_distance_to_the_wall(room):
    # Rays of the depth sensor that hit the wall only: they see the room's y position and tilt.
    plan = mbcal.measurements_from_records(
        [{"kind": "range", "sensor": "depth", "ray": k, "sigma": 0.002} for k in range(192)], room
    )
    scene = mbcal.modeler(room, room.nominal)
    from mbcal.geometry.raycast import scene_cast_rays

    origins, directions = scene.range_rays("depth")
    on_wall = np.asarray(scene_cast_rays(scene, origins, directions, shapes=["room.wall"]))
    everything = np.asarray(scene_cast_rays(scene, origins, directions))
    wall_only = np.isclose(on_wall, everything) & (np.abs(np.arange(192) % 16 - 7.5) > 5)
    plan = plan.subset(wall_only)
    assert len(plan) >= 20
    truth = {"room.y": 0.03, "room.yaw": math.radians(1.5)}
    data = mbcal.simulate(room, plan, truth, seed=4)
    result = mbcal.calibrate(room, data, ["room.y", "room.yaw"], restarts=4)
    assert result.ok
    assert_within_3_sigma(result, truth)
    assert result.std["room.y"] < 0.001


@pytest.mark.slow
def test_points_on_surfaces_recover_the_room_pose(room):
    # A point cloud in the depth sensor's frame (from its rays at the true pose) fitted to the
    # room's surfaces: the seed's "automatic calibration" with a range sensor.
    truth = dict(ROOM_TRUTH)
    scene = mbcal.modeler(room, mbcal.parameter_vector(room, truth))
    from mbcal.geometry.raycast import scene_cast_rays

    origins, directions = scene.range_rays("depth")
    t = np.asarray(scene_cast_rays(scene, origins, directions))
    hit = np.isfinite(t)
    T = np.asarray(scene.frame("depth"))
    world = np.asarray(origins)[hit] + np.asarray(directions)[hit] * t[hit, None]
    local = (world - T[:3, 3]) @ T[:3, :3] + np.random.default_rng(2).normal(0, 0.001, world.shape)
    records = [
        {
            "kind": "point_to_surface",
            "object": "room",
            "frame": "depth",
            "x": p[0],
            "y": p[1],
            "z": p[2],
            "sigma": 0.002,
        }
        for p in local
    ]
    data = mbcal.measurements_from_records(records, room)
    result = mbcal.calibrate(room, data, ["room.*"], restarts=8, seed=3)
    assert result.converged
    assert_within_3_sigma(result, truth)


def test_models_from_text_with_the_same_structure_do_not_share_a_compiled_program():
    # Two texts that differ only in a constant: the cache key (fingerprint) must tell them apart,
    # or a second process could solve the second model with the first one's compiled program.
    from mbcal.problem import Problem

    def problem(x: str) -> Problem:
        model = mbcal.load_model_text(f"param a = 1 m in [0 m, 2 m]\npoint p = (a, {x}, 0)\nmeasure point3d")
        plan = mbcal.measurements_from_records([{"kind": "point3d", "point": "p", "sigma": 0.01}], model)
        return Problem(model, plan, ["a"])

    assert problem("0.5 m").fingerprint() != problem("0.7 m").fingerprint()
    assert problem("0.5 m").fingerprint() == problem("0.5 m").fingerprint()


def test_point_uncertainties_group_equal_jacobian_patterns_exactly():
    """observability._equal_rows groups equal boolean rows (what np.unique(axis=0) does, faster),
    and a (k, 3) eye array with NaN rows gives what the list of eyes with None gives."""
    from mbcal.observability import _equal_rows, point_uncertainties

    rng = np.random.default_rng(3)
    for n in (1, 7, 64, 65, 130):
        rows = rng.random((200, n)) < 0.5
        rows[50:80] = rows[0]  # some repeated patterns
        order, starts = _equal_rows(rows)
        assert sorted(order.tolist()) == list(range(200))
        groups = np.split(order, starts[1:])
        assert len(groups) == len(np.unique(rows, axis=0))
        for g in groups:
            assert (rows[g] == rows[g[0]]).all()
        firsts = [rows[g[0]].tobytes() for g in groups]
        assert len(set(firsts)) == len(firsts)  # different groups, different rows

    k, n = 6, 5
    P = rng.normal(size=(k, 3))
    J = rng.normal(size=(k, 3, n)) * (rng.random((k, 1, n)) < 0.7)
    A = rng.normal(size=(n, n))
    cov = A @ A.T
    eyes_list = [None if i % 3 == 0 else rng.normal(size=3) for i in range(k)]
    eyes_array = np.array([np.full(3, np.nan) if e is None else e for e in eyes_list])
    items = [(f"p{i}", "c", None) for i in range(k)]
    a = point_uncertainties(items, P, J, cov, eyes_list)
    b = point_uncertainties(items, P, J, cov, eyes_array)
    for u, v in zip(a, b):
        np.testing.assert_allclose(u.covariance, J[int(u.point[1:])] @ cov @ J[int(u.point[1:])].T, rtol=1e-12)
        np.testing.assert_array_equal(u.covariance, v.covariance)
        assert (np.isnan(u.parallel) and np.isnan(v.parallel)) or u.parallel == v.parallel
        assert u.perpendicular == v.perpendicular


@pytest.mark.slow
def test_point_uncertainties_from_block_jacobians_equal_the_dense_ones():
    """A camera calibration's point uncertainties come from each point's compressed Jacobian
    (its view's block and the intrinsics) and its block's joint covariance; they equal the dense
    propagation through the full k × 3 × n Jacobian."""
    from mbcal.observability import point_uncertainties
    from mbcal.structured import block_point_uncertainties, joint_from_dense, structure_of
    from mbcal.workflows.cameras import calibrate_cameras, simulate_views

    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data, _ = simulate_views(model, 9, {"cam.fx": 805.0, "cam.k1": -0.15}, seed=5, sigma=0.3)
    result = calibrate_cameras(model, data, restarts=1).result
    problem, x, cov = result.problem, result.x, result.covariance
    structure = structure_of(problem)
    assert structure is not None and structure.n_blocks == 9
    pts = result.points
    assert len(pts) == len(data)
    configs = problem.params.configurations
    cfg_idx = np.array([configs.index(p.configuration) for p in pts])
    idx = np.array([model.point_index(p.point) for p in pts])
    items = [(p.point, p.configuration, p.camera) for p in pts]
    eyes = [None] * len(pts)  # no line of sight: only the covariances are compared
    P, J = problem.point_jacobian(x, cfg_idx, idx)
    dense = point_uncertainties(items, P, J, cov, eyes)
    joint = joint_from_dense(structure, cov)
    blocks = block_point_uncertainties(problem, structure, joint, x, cfg_idx, idx, items, eyes)
    for d, b, p in zip(dense, blocks, pts):
        np.testing.assert_allclose(b.covariance, d.covariance, rtol=1e-9, atol=1e-22)
        np.testing.assert_allclose(p.covariance, d.covariance, rtol=1e-9, atol=1e-22)  # what the report holds
        np.testing.assert_allclose(b.position, d.position, rtol=0, atol=1e-12)


def test_a_problem_without_cameras_reports_its_points_largest_sigma_not_an_infinite_one_along_no_line_of_sight():
    # 3-D measurements only (a robot's link origins, a CMM): no camera, no line of sight to split the
    # uncertainty along; the report gave σ∥ = ∞ for every point of a well determined fit.
    model = mbcal.load_model_text(
        "param a = 1 m in [0 m, 2 m]\nparam b = 0.2 m in [0 m, 1 m]\npoint p = (a, b, 0)\npoint q = (a, 0, b)\n"
        "measure point3d"
    )
    plan = mbcal.measurements_from_records(
        [{"kind": "point3d", "point": name, "sigma": 0.01} for name in ("p", "q")], model
    )
    data = mbcal.simulate(model, plan, {"a": 1.1, "b": 0.25}, noise=1.0, seed=0)
    result = mbcal.calibrate(model, data, ["a", "b"], restarts=2)
    assert result.converged and all(p.camera is None for p in result.points)
    text = result.summary()
    section = text.split("position uncertainty of the points")[1].split("\n\n")[0]
    assert "no camera: the largest σ in any direction" in section
    assert "∞" not in section and "line of sight" not in section.splitlines()[1]
    for p in result.points:
        assert np.isfinite(p.perpendicular) and np.isnan(p.parallel)
        assert f"{1000 * p.perpendicular:.3g}" in section
    (row,) = [line for line in section.splitlines() if line.startswith("p ")]
    assert row.split()[-2] == f"{1000 * result.points[0].perpendicular:.3g}"
    assert row.split()[-1] == f"{1000 * result.points[0].total:.3g}"


def test_the_model_summary_counts_in_the_singular_and_the_plural():
    from mbcal.language.summary import model_summary

    model = mbcal.load_model_text("camera c(width = 8, height = 6, f = 4)\npoint p = (0, 0, 1)\npoint q = (0, 1, 1)")
    counts = model_summary(model).splitlines()[1]
    assert "1 camera," in counts and "2 points" in counts and "0 range sensors" in counts and "0 shapes" in counts


def test_a_robust_fit_does_not_call_its_robust_cost_a_chi2():
    """With a robust loss, S is Σρ(r²): the header called Σρ/dof the reduced χ² while the fit verdict
    below tested the plain squares."""
    from mbcal.solver import SolverConfig

    model = mbcal.load_model_text(
        "param a = 1 m in [0 m, 2 m]\nparam b = 0.2 m in [0 m, 1 m]\n"
        + "".join(f"point p{k} = (a + {0.1 * k} m, b, {0.05 * k} m)\n" for k in range(6))
        + "measure point3d"
    )
    plan = mbcal.measurements_from_records(
        [{"kind": "point3d", "point": f"p{k}", "sigma": 0.01} for k in range(6)], model
    )
    data = mbcal.simulate(model, plan, {"a": 1.1, "b": 0.25}, noise=1.0, seed=0)
    robust = mbcal.calibrate(model, data, ["a", "b"], restarts=2, config=SolverConfig(loss="cauchy"))
    plain = mbcal.calibrate(model, data, ["a", "b"], restarts=2)
    head = robust.summary().splitlines()[1]
    assert head.startswith(f"S = Σρ(r²) = {robust.cost:.6g} (cauchy loss)") and "Σρ/dof = " in head
    assert "χ²" not in head and head.endswith(f"RMS: point3d {robust.rms['point3d']:.4g} m")
    plain_head = plain.summary().splitlines()[1]
    assert plain_head.startswith(f"S = {plain.cost:.6g} over 18 residuals") and "reduced χ² = " in plain_head
