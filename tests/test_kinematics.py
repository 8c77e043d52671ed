"""Kinematics from the model: f(θ) and J against yourdfpy, the modeler and finite differences;
J J* = I; the damped J* at a singularity; inverse kinematics (reachable, unreachable, limits,
orientation, batches); float64 whatever the caller did; errors; the ``mbcal kinematics`` command."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import yourdfpy

import mbcal
from mbcal.cli import main
from mbcal.errors import KinematicsError, UnknownNameError, UnreachableError
from mbcal.kinematics import Kinematics, manipulability, pseudo_inverse

from conftest import MODELS, ROOT

URDF = ROOT / "tests" / "data" / "arm7.urdf"
JOINTS = [f"joint{i}" for i in range(1, 8)]


@pytest.fixture(scope="module")
def urdf_model():
    return mbcal.load_model(URDF)


@pytest.fixture(scope="module")
def urdf_arm(urdf_model):
    return Kinematics(urdf_model, "tool_center")


@pytest.fixture(scope="module")
def robot():
    return yourdfpy.URDF.load(str(URDF), load_meshes=False)


@pytest.fixture(scope="module")
def seed_model():
    return mbcal.load_model(MODELS / "arm7.mdl")


@pytest.fixture(scope="module")
def seed_arm(seed_model):
    return Kinematics(seed_model, "hand.tip", chain="arm.q*")


def within_limits(kin: Kinematics, count: int, seed: int, margin: float = 0.05) -> np.ndarray:
    lo = np.where(np.isfinite(kin.lower), kin.lower + margin, -np.pi)
    hi = np.where(np.isfinite(kin.upper), kin.upper - margin, np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(count, kin.n))


def yourdfpy_pose(robot, q: np.ndarray, link: str = "tool-center") -> np.ndarray:
    robot.update_cfg(dict(zip(JOINTS, q)))
    return robot.get_transform(link, robot.base_link)


def fd_jacobian(pose_of, theta: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """(6, n) by central differences of a pose function θ → (4, 4): dp/dθ and vee(dR/dθ Rᵀ)."""
    R = pose_of(theta)[:3, :3]
    cols = []
    for k in range(len(theta)):
        d = np.zeros(len(theta))
        d[k] = h
        plus, minus = pose_of(theta + d), pose_of(theta - d)
        v = (plus[:3, 3] - minus[:3, 3]) / (2 * h)
        W = (plus[:3, :3] - minus[:3, :3]) / (2 * h) @ R.T
        cols.append(np.concatenate([v, [W[2, 1], W[0, 2], W[1, 0]]]))
    return np.stack(cols, axis=1)


def assert_jacobian_close(J: np.ndarray, reference: np.ndarray) -> None:
    """≤ 1e-7 relative to the matrix's scale (the issue's bound for finite differences)."""
    scale = np.abs(reference).max()
    assert np.abs(J - reference).max() <= 1e-7 * scale, np.abs(J - reference).max() / scale


# ---- f and J --------------------------------------------------------------------------------------------


def test_the_chain_defaults_to_the_joints_between_the_world_and_the_target(urdf_arm, seed_model):
    assert urdf_arm.joints == [f"{j}.q" for j in JOINTS]
    assert urdf_arm.fast and urdf_arm.target.endswith("tool_center") and urdf_arm.what == "frame"
    np.testing.assert_allclose(urdf_arm.lower[0], -2.9)
    np.testing.assert_allclose(urdf_arm.upper[3], 0.5)
    assert Kinematics(seed_model, "hand.tip").joints == ["torso.q", *(f"arm.q{i}" for i in range(1, 8))]
    by_frame = Kinematics(seed_model, "hand.tip", chain="shoulder_flexion, elbow")
    assert by_frame.joints == ["arm.q1", "arm.q4"]


def test_pose_equals_yourdfpys_forward_kinematics(urdf_arm, robot):
    Q = within_limits(urdf_arm, 20, seed=1)
    poses = np.asarray(urdf_arm.pose(Q))
    for q, T in zip(Q, poses):
        np.testing.assert_allclose(T, yourdfpy_pose(robot, q), rtol=0, atol=1e-9)


def test_jacobian_equals_finite_differences_of_yourdfpy(urdf_arm, robot):
    for q in within_limits(urdf_arm, 5, seed=2):
        J = np.asarray(urdf_arm.jacobian(q))
        assert_jacobian_close(J, fd_jacobian(lambda t: yourdfpy_pose(robot, t), q))


def test_a_link_in_the_middle_and_a_partial_chain(urdf_model, robot):
    kin = Kinematics(urdf_model, "link4", chain="joint2.q, joint4.q")
    rng = np.random.default_rng(3)
    for _ in range(3):
        q = rng.uniform(-1.0, 1.0, size=7)
        q[[0, 2, 4, 5, 6]] = 0.0  # the variables outside the chain at their nominal value
        T = np.asarray(kin.pose(q[[1, 3]]))
        np.testing.assert_allclose(T, yourdfpy_pose(robot, q, "link4"), rtol=0, atol=1e-9)
        J = np.asarray(kin.jacobian(q[[1, 3]]))

        def pose(t, q=q):
            full = q.copy()
            full[[1, 3]] = t
            return yourdfpy_pose(robot, full, "link4")

        assert_jacobian_close(J, fd_jacobian(pose, q[[1, 3]]))


def test_the_seed_arm_agrees_with_the_modeler_and_finite_differences(seed_model, seed_arm):
    X = seed_model.nominal.copy()

    def modeler_pose(t):
        X[seed_arm.indices] = t
        scene = mbcal.modeler(seed_model, X)
        T = np.asarray(scene.frame(seed_model.frames[seed_arm.frame].name)).copy()
        T[:3, 3] = np.asarray(scene.point("hand.tip"))
        return T

    for q in within_limits(seed_arm, 4, seed=4):
        np.testing.assert_allclose(np.asarray(seed_arm.pose(q)), modeler_pose(q), rtol=0, atol=1e-12)
        assert_jacobian_close(np.asarray(seed_arm.jacobian(q)), fd_jacobian(modeler_pose, q))


def test_calibrated_values_move_the_hand(seed_model, seed_arm):
    values = {"arm.offset2": 0.03, "arm.offset4": -0.02}
    shifted = Kinematics(seed_model, "hand.tip", chain="arm.q*", values=values)
    q = np.radians([10, -30, 0, -60, 0, 20, 0])
    moved = q + np.array([0, 0.03, 0, -0.02, 0, 0, 0])  # an offset adds to the reading
    np.testing.assert_allclose(np.asarray(shifted.pose(q)), np.asarray(seed_arm.pose(moved)), atol=1e-14)


def test_the_general_evaluator_for_a_variable_that_enters_twice(write_model):
    model = mbcal.load_model(
        write_model(
            """
            param a = 0 deg
            param b = 0 deg
            param c = 0.1 m
            frame base {
              link l1 at (0, 0, 0.5 m) {
                joint revolute(z, a)
                link l2 at translate(0.3 m, 0, 0) * rot_x(b) {
                  joint revolute(y, b)
                  link l3 at (0.2 m, 0, 0) {
                    joint prismatic(x, c)
                    point tip = (0.05 m, 0, 0.1 m)
                  }
                }
              }
            }
            """
        )
    )
    kin = Kinematics(model, "tip", chain="a,b,c")
    assert not kin.fast  # b moves a pose and a joint: J comes from jacfwd
    X = model.nominal.copy()

    def pose(t):
        X[kin.indices] = t
        scene = mbcal.modeler(model, X)
        T = np.asarray(scene.frame("l3")).copy()
        T[:3, 3] = np.asarray(scene.point("tip"))
        return T

    for t in ([0.3, -0.4, 0.05], [1.1, 0.7, 0.2]):
        np.testing.assert_allclose(np.asarray(kin.pose(t)), pose(np.array(t)), atol=1e-12)
        assert_jacobian_close(np.asarray(kin.jacobian(t)), fd_jacobian(pose, np.array(t)))


MIMIC = """<?xml version="1.0"?>
<robot name="mimic">
  <link name="base"/> <link name="a"/> <link name="b"/> <link name="c"/>
  <joint name="j1" type="revolute">
    <parent link="base"/><child link="a"/><origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="j2" type="revolute">
    <parent link="a"/><child link="b"/><origin xyz="0.3 0 0" rpy="0.1 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="b"/><child link="c"/><origin xyz="0.25 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
    <mimic joint="j2" multiplier="0.5" offset="0.1"/>
  </joint>
</robot>
"""


def test_a_urdf_mimic_joint_against_yourdfpy(tmp_path):
    path = tmp_path / "mimic.urdf"
    path.write_text(MIMIC, encoding="utf-8")
    kin = Kinematics(mbcal.load_model(path), "c", what="frame")
    assert kin.joints == ["j1.q", "j2.q"] and not kin.fast  # j2 drives two joints
    robot = yourdfpy.URDF.load(str(path), load_meshes=False)

    def pose(q):
        robot.update_cfg({"j1": q[0], "j2": q[1]})
        return robot.get_transform("c", robot.base_link)

    for q in (np.array([0.3, -0.4]), np.array([1.0, 0.7])):
        np.testing.assert_allclose(np.asarray(kin.pose(q)), pose(q), atol=1e-12)
        assert_jacobian_close(np.asarray(kin.jacobian(q)), fd_jacobian(pose, q))


def test_the_fast_and_the_general_evaluator_agree(seed_model):
    fast = Kinematics(seed_model, "hand.thumb", chain="torso.q, arm.q*")
    general = Kinematics(seed_model, "hand.thumb", chain="torso.q, arm.q*")
    general._segments = None  # force the modeler-like walk with jax.jacfwd
    assert fast.fast and not general.fast
    Q = np.random.default_rng(5).uniform(-2, 2, size=(6, 8))
    a, b = fast.forward(Q), general.forward(Q)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-13)


@pytest.mark.slow
def test_batches_keep_their_leading_axes_and_match_single_calls(seed_arm):
    Q = np.random.default_rng(6).uniform(-1, 1, size=(2, 3, 7))
    out = seed_arm.forward(Q)
    assert out.position.shape == (2, 3, 3) and out.rotation.shape == (2, 3, 3, 3) and out.jacobian.shape == (2, 3, 6, 7)
    assert seed_arm.pose(Q).shape == (2, 3, 4, 4) and seed_arm.manipulability(Q).shape == (2, 3)
    assert seed_arm.pseudo_inverse(Q, part="position").shape == (2, 3, 7, 3)
    single = seed_arm.forward(Q[1, 2])
    np.testing.assert_allclose(np.asarray(out.jacobian[1, 2]), np.asarray(single.jacobian), atol=1e-15)


@pytest.mark.slow
def test_forward_single_is_a_pure_function_for_jit_and_vmap(seed_arm):
    from mbcal._jax import jax, jnp

    Q = jnp.asarray(np.random.default_rng(7).uniform(-1, 1, size=(5, 7)))
    mapped = jax.jit(jax.vmap(seed_arm.forward_single))(Q)
    batch = seed_arm.forward(Q)
    np.testing.assert_allclose(np.asarray(mapped.jacobian), np.asarray(batch.jacobian), atol=1e-14)
    # And its J is the derivative of its own position.
    auto = jax.jacfwd(lambda q: seed_arm.forward_single(q).position)(Q[0])
    np.testing.assert_allclose(np.asarray(auto), np.asarray(batch.jacobian[0, :3]), atol=1e-13)


def test_local_axes_rotate_both_halves(urdf_arm):
    q = within_limits(urdf_arm, 1, seed=8)[0]
    R = np.asarray(urdf_arm.pose(q))[:3, :3]
    J = np.asarray(urdf_arm.jacobian(q))
    Jl = np.asarray(urdf_arm.jacobian(q, frame="local"))
    np.testing.assert_allclose(Jl[:3], R.T @ J[:3], atol=1e-14)
    np.testing.assert_allclose(Jl[3:], R.T @ J[3:], atol=1e-14)
    np.testing.assert_allclose(np.asarray(urdf_arm.jacobian(q, part="orientation")), J[3:], atol=0)


# ---- J*, damping, manipulability --------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("part, rows", [("position", 3), ("full", 6)])
def test_j_times_j_star_is_the_identity_away_from_singularities(urdf_arm, part, rows):
    Q = within_limits(urdf_arm, 50, seed=9)
    w = np.asarray(urdf_arm.manipulability(Q, part=part))
    Q = Q[w > 1e-3 * w.max()]
    J = np.asarray(urdf_arm.jacobian(Q, part=part))
    Js = np.asarray(urdf_arm.pseudo_inverse(Q, part=part))
    assert len(Q) > 30
    np.testing.assert_allclose(J @ Js, np.broadcast_to(np.eye(rows), (len(Q), rows, rows)), atol=1e-10)
    # J* is the minimum-norm right inverse: Jᵀ(JJᵀ)⁻¹ = pinv(J) for full row rank.
    np.testing.assert_allclose(Js, np.linalg.pinv(J), atol=1e-9)


def test_the_damped_inverse_stays_finite_at_a_singular_configuration(seed_arm):
    straight = np.zeros(7)  # the arm hanging straight down: the tip cannot move vertically
    assert float(seed_arm.manipulability(straight, part="position")) == 0.0
    assert not np.isfinite(np.asarray(seed_arm.pseudo_inverse(straight, part="position"))).any()
    for damping in (1e-3, 1e-2, 0.1):
        D = np.asarray(seed_arm.damped_pseudo_inverse(straight, damping, part="position"))
        assert np.isfinite(D).all() and np.abs(D).max() < 10.0
    # Away from the singularity the damped inverse tends to J* as λ → 0.
    q = np.radians([10, -30, 0, -60, 0, 20, 0])
    exact = np.asarray(seed_arm.pseudo_inverse(q, part="position"))
    np.testing.assert_allclose(np.asarray(seed_arm.damped_pseudo_inverse(q, 1e-6, part="position")), exact, atol=1e-8)


def test_the_pure_functions_of_j():
    J = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    np.testing.assert_allclose(np.asarray(pseudo_inverse(J)), np.linalg.pinv(J), atol=1e-15)
    assert float(manipulability(J)) == pytest.approx(2.0)
    assert float(manipulability(np.array([[1.0, 0.0], [2.0, 0.0]]))) == 0.0


def test_a_chain_with_fewer_joints_than_rows_gets_the_least_squares_inverse(seed_model, capsys):
    """Two joints for three position rows: JJᵀ (3 × 3, rank 2) is never invertible, and every
    configuration was called singular ('give a damping'), exit 1."""
    J = np.array([[1.0, 0.5], [0.0, 2.0], [3.0, -1.0]])
    np.testing.assert_allclose(np.asarray(pseudo_inverse(J)), np.linalg.pinv(J), atol=1e-14)
    np.testing.assert_allclose(np.asarray(pseudo_inverse(J, 0.3)), J.T @ np.linalg.inv(J @ J.T + 0.09 * np.eye(3)))
    assert float(manipulability(J)) == pytest.approx(np.prod(np.linalg.svd(J, compute_uv=False)), rel=1e-14)
    assert not np.isfinite(np.asarray(pseudo_inverse(np.array([[1.0, 2.0], [2.0, 4.0], [0.0, 0.0]])))).any()
    short = Kinematics(seed_model, "hand.tip", chain="arm.q1,arm.q2")
    q = np.radians([-30.0, 20.0])
    Jp = np.asarray(short.jacobian(q, part="position"))
    L = np.asarray(short.pseudo_inverse(q, part="position"))
    np.testing.assert_allclose(L, np.linalg.pinv(Jp), atol=1e-12)
    np.testing.assert_allclose(L @ Jp, np.eye(2), atol=1e-12)
    w = float(short.manipulability(q, part="position"))
    assert w == pytest.approx(np.prod(np.linalg.svd(Jp, compute_uv=False)), rel=1e-12) and w > 0.1
    text, data = short.report(q)
    assert not data["singular"] and data["pseudo_inverse"]["inverse"] == "left"
    assert "J* = (JᵀJ)⁻¹Jᵀ of the position rows — the chain has fewer joints (2) than rows (3)" in text
    assert "manipulability √det(JᵀJ)" in text and "singular" not in text
    argv = ["kinematics", str(MODELS / "arm7.mdl"), "--point", "hand.tip", "--chain", "arm.q1,arm.q2"]
    assert main([*argv, "--joints=-30deg,20deg"]) == 0
    assert "least-squares joint step" in capsys.readouterr().out
    # seven joints for six rows: the seed's right inverse, as before
    assert (
        Kinematics(seed_model, "hand.tip", chain="arm.q*").report(np.radians([10, -30, 0, -60, 0, 20, 0]))[1][
            "pseudo_inverse"
        ]["inverse"]
        == "right"
    )


# ---- inverse kinematics -------------------------------------------------------------------------------------


@pytest.mark.slow
def test_ik_reaches_reachable_targets_within_the_joint_limits(urdf_arm):
    Q = within_limits(urdf_arm, 12, seed=10)
    targets = np.asarray(urdf_arm.position(Q))
    result = urdf_arm.ik(targets, restarts=8, seed=0)
    assert result.reached.all() and result.unreachable == []
    assert result.distance.max() <= 1e-9
    np.testing.assert_allclose(np.asarray(urdf_arm.position(result.theta)), targets, atol=1e-9)
    assert (result.theta >= urdf_arm.lower - 1e-12).all() and (result.theta <= urdf_arm.upper + 1e-12).all()


@pytest.mark.slow
def test_ik_with_orientation_and_a_single_target(urdf_arm):
    q = within_limits(urdf_arm, 1, seed=11)[0]
    T = np.asarray(urdf_arm.pose(q))
    result = urdf_arm.ik(T[:3, 3], orientation=T[:3, :3], restarts=16, seed=1)
    assert result.single and result.theta.shape == (7,)
    assert result.reached and result.distance <= 1e-9 and result.angle <= 1e-9
    np.testing.assert_allclose(np.asarray(urdf_arm.pose(result.theta)), T, atol=1e-9)


@pytest.mark.slow
def test_ik_prefers_the_solution_nearest_the_initial_values(seed_arm):
    q = np.radians([10, -30, 5, -60, 10, 20, -5])
    result = seed_arm.ik(seed_arm.position(q), initial=q + 0.05, restarts=8)
    assert result.reached
    # A redundant arm has a curve of solutions; the one kept is on the branch the start was on.
    assert np.linalg.norm(result.theta - (q + 0.05)) < 0.5


@pytest.mark.slow
def test_ik_names_unreachable_targets_with_the_closest_pose_and_distance(seed_arm):
    targets = np.array([[0.35, -0.4, 0.95], [2.0, 0.0, 1.0]])
    result = seed_arm.ik(targets, restarts=8)
    assert result.reached.tolist() == [True, False] and result.unreachable == [1]
    shoulder = np.asarray(Kinematics(seed_arm.model, "shoulder_flexion", chain="arm.q1").position([0.0]))
    reach = 0.186 * 1.75 + 0.146 * 1.75 + 0.108 * 1.75  # upper arm + forearm + hand
    assert result.distance[1] == pytest.approx(np.linalg.norm(targets[1] - shoulder) - reach, abs=1e-6)
    np.testing.assert_allclose(np.asarray(seed_arm.position(result.theta[1])), result.position[1], atol=1e-12)
    text = result.report()
    assert "target 1" in text and "out of reach for hand.tip" in text and "closest pose" in text
    with pytest.raises(UnreachableError, match="out of reach") as err:
        result.check()
    assert err.value.exit_code == 1
    data = result.to_json()
    assert data["targets"][1]["reached"] is False and data["targets"][1]["distance"] > 1.0


@pytest.mark.slow
def test_ik_respects_joint_limits_for_a_target_only_reachable_beyond_them(urdf_model):
    kin = Kinematics(urdf_model, "tool_center")
    q = np.zeros(7)
    q[3] = 1.2  # joint4 is limited to [-2.5, 0.5]
    result = kin.ik(kin.position(q), restarts=16, seed=2)
    assert (result.theta >= kin.lower).all() and (result.theta <= kin.upper).all()


TWICE = """
param q = 0 deg per configuration
param r = 0 deg per configuration
object a at (0, 0, 0) {
  joint revolute(z, q)
  object b at (0.3 m, 0, 0) {
    joint revolute(z, 0.5 * q)
    object c at (0.2 m, 0, 0) {
      joint revolute(z, r)
      point tip = (0.1 m, 0, 0)
    }
  }
}
"""

# j3 mimics the continuous j1 (−0.5 · j1 + 0.2, limited to ±2 rad); j4 is on the point's axis
MIX = """<?xml version="1.0"?>
<robot name="mix">
  <link name="base"/><link name="a"/><link name="b"/><link name="c"/><link name="d"/>
  <joint name="j1" type="continuous"><parent link="base"/><child link="a"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 -0.2 0.5"/><axis xyz="0 0 2"/></joint>
  <joint name="j2" type="prismatic"><parent link="a"/><child link="b"/><origin xyz="0.2 0 0.05" rpy="0 0.4 0"/>
    <axis xyz="0.6 0.8 0"/><limit lower="-0.1" upper="0.3" effort="1" velocity="1"/></joint>
  <joint name="j3" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0 0.15 0" rpy="-0.7 0 0.1"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/>
    <mimic joint="j1" multiplier="-0.5" offset="0.2"/></joint>
  <joint name="j4" type="revolute"><parent link="c"/><child link="d"/><origin xyz="0.1 0 0.2" rpy="0 0 0"/>
    <axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>
"""


def twice_position(q: float, r: float) -> np.ndarray:
    """The tip of TWICE by hand: the second joint turns by q/2 on top of q."""
    angles = np.cumsum([q, 0.5 * q, r])
    return sum(length * np.array([np.cos(a), np.sin(a), 0.0]) for length, a in zip((0.3, 0.2, 0.1), angles))


@pytest.mark.slow
def test_ik_wraps_only_variables_the_pose_repeats_in_after_a_full_turn(write_model):
    """q turns one joint by q and the next by q/2: the pose has period 4π in q, not 2π.  IK found
    q = 250° from that very start, brought it to −110° (another pose, 0.6 m away) and said the
    target was out of reach."""
    kin = Kinematics(mbcal.load_model(write_model(TWICE)), "tip")
    assert kin.joints == ["q", "r"] and kin.periodic.tolist() == [False, True]
    theta = np.radians([250.0, 10.0])
    target = twice_position(*theta)
    np.testing.assert_allclose(np.asarray(kin.position(theta)), target, atol=1e-15)
    assert np.linalg.norm(twice_position(theta[0] - 2 * np.pi, theta[1]) - target) > 0.5
    for start in (theta, np.radians([0.0, 370.0])):
        result = kin.ik(target, initial=start, restarts=4)
        assert result.reached and result.distance <= 1e-9, result.report()
        np.testing.assert_allclose(twice_position(*result.theta), target, atol=1e-9)
        np.testing.assert_allclose(np.asarray(kin.position(result.theta)), result.position, atol=1e-15)
        assert -np.pi < result.theta[1] <= np.pi  # r alone turns a joint: wrapped
    # every variable a revolute angle of its own: wrapped as before
    serial = Kinematics(mbcal.load_model(write_model(TWICE.replace("0.5 * q", "r"), "serial.mdl")), "tip")
    assert serial.periodic.tolist() == [True, True]


@pytest.mark.slow
def test_ik_keeps_a_continuous_joint_that_a_mimic_follows_unwrapped(tmp_path):
    path = tmp_path / "mix.urdf"
    path.write_text(MIX, encoding="utf-8")
    kin = Kinematics(mbcal.load_model(path), "d", what="frame")
    assert kin.joints == ["j1.q", "j2.q", "j4.q"] and not kin.periodic.any()
    robot = yourdfpy.URDF.load(str(path), load_meshes=False)
    theta = np.array([4.0, 0.1, 0.3])  # j3 = −1.8 rad, within its limits
    robot.update_cfg({"j1": theta[0], "j2": theta[1], "j4": theta[2]})
    target = robot.get_transform("d", robot.base_link)[:3, 3]
    np.testing.assert_allclose(np.asarray(kin.position(theta)), target, atol=1e-12)
    result = kin.ik(target, initial=theta, restarts=4)
    assert result.reached and result.distance <= 1e-9, result.report()
    robot.update_cfg(dict(zip(["j1", "j2", "j4"], result.theta)))
    np.testing.assert_allclose(robot.get_transform("d", robot.base_link)[:3, 3], target, atol=1e-9)


def test_a_joint_the_chain_drives_outside_its_limits_is_named(tmp_path, write_model, capsys):
    """j3 mimics j1 (−0.5 · j1 + 0.2, limits ±2 rad): at j1 = 10 rad it is at −4.8 rad, and the
    report said nothing (outside_limits [], exit 0) — only the chain's own variables were checked."""
    path = tmp_path / "mix.urdf"
    path.write_text(MIX, encoding="utf-8")
    kin = Kinematics(mbcal.load_model(path), "d", what="frame")
    assert kin.driven == ["j3"]  # a URDF joint by its own name
    Q = np.array([[10.0, 0.1, 0.3], [4.0, 0.1, 0.3], [-3.0, 0.0, 0.0]])
    np.testing.assert_allclose(kin.driven_values(Q)[:, 0], -0.5 * Q[:, 0] + 0.2, atol=1e-15)
    text, data = kin.report(Q[0])
    assert "outside the joint limits: j3" in text and data["outside_limits"] == ["j3"]
    limits = {"lower": pytest.approx(-2.0, abs=1e-14), "upper": pytest.approx(2.0, abs=1e-14)}  # via degrees
    assert data["driven"] == [{"name": "j3", "value": pytest.approx(-4.8, abs=1e-15), "unit": "rad", **limits}]
    assert kin.report(Q[1])[1]["outside_limits"] == []
    assert main(["kinematics", str(path), "--point", "d", "--joints=10,0.1,0.3", "--json", "-"]) == 1
    out = capsys.readouterr().out
    assert json.loads(out[out.index("{") :])["outside_limits"] == ["j3"]
    # a parameter that drives a second joint by 0.5 * q: that joint by its frame's name, in degrees
    limited = TWICE.replace("0.5 * q)", "0.5 * q, lower = -60 deg, upper = 60 deg)")
    twice = Kinematics(mbcal.load_model(write_model(limited)), "tip")
    assert twice.driven == ["a.b"] and twice.periodic.tolist() == [False, True]
    text, data = twice.report(np.radians([250.0, 10.0]))
    assert "outside the joint limits: a.b" in text and re.search(r"\na\.b +125 +deg +-60 +60\n", text), text


@pytest.mark.slow
def test_ik_keeps_the_joints_the_chain_drives_within_their_limits(tmp_path):
    path = tmp_path / "mix.urdf"
    path.write_text(MIX, encoding="utf-8")
    kin = Kinematics(mbcal.load_model(path), "d", what="frame")
    # j1 = 10 rad puts j3 at −4.8 rad; j1 = 10 − 4π reaches the same point with j3 = 1.48 rad
    start = np.array([10.0, 0.1, 0.3])
    target = np.asarray(kin.position(start))
    result = kin.ik(target, initial=start, restarts=8)
    assert result.reached and result.distance <= 1e-9 and result.outside_limits == ()
    assert abs(-0.5 * result.theta[0] + 0.2) <= 2.0
    np.testing.assert_allclose(np.asarray(kin.position(result.theta)), target, atol=1e-9)
    # j1 = 6 rad (j3 = −2.8 rad): no θ within the limits puts d there; the closest found is not
    # called reached, and a j3 left outside its limits is named
    start = np.array([6.0, 0.1, 0.3])
    result = kin.ik([target, np.asarray(kin.position(start))], initial=start, restarts=8)
    assert result.reached.tolist() == [True, False] and result.unreachable == [1]
    beyond = not -2.0 - 1e-6 <= -0.5 * result.theta[1, 0] + 0.2 <= 2.0 + 1e-6
    assert result.outside_limits[1] == (("j3",) if beyond else ())
    assert (result.distance[1] > 1e-6) or beyond
    assert result.to_json()["targets"][1]["outside_limits"] == list(result.outside_limits[1])
    # the reported θ at the boundary, the target met exactly: reached only within the limits
    at_edge = np.array([-3.6, 0.1, 0.3])  # j3 = 2 rad exactly
    result = kin.ik(np.asarray(kin.position(at_edge)), initial=at_edge - [0.3, 0.0, 0.0], restarts=4)
    assert result.reached and -0.5 * result.theta[0] + 0.2 <= 2.0 + 1e-6


# ---- float64 ------------------------------------------------------------------------------------------------


def test_float32_inputs_give_float64_results(seed_arm):
    from mbcal._jax import jnp

    q64 = np.radians([10, -30, 0, -60, 0, 20, 0])
    q32 = jnp.asarray(q64, dtype=jnp.float32)
    J = seed_arm.jacobian(q32)
    assert J.dtype == np.float64
    np.testing.assert_allclose(np.asarray(J), np.asarray(seed_arm.jacobian(np.asarray(q32, dtype=np.float64))), atol=0)


@pytest.mark.slow
def test_float64_even_when_the_caller_made_float32_arrays_before_mbcal_and_turned_x64_off():
    code = """
import jax, jax.numpy as jnp, numpy as np
theta = jnp.asarray(np.radians([10, -30, 0, -60, 0, 20, 0]))    # before mbcal: float32
assert theta.dtype == jnp.float32
import mbcal
from mbcal.kinematics import Kinematics
arm = Kinematics(mbcal.load_model("models/arm7.mdl"), "hand.tip", chain="arm.q*")
jax.config.update("jax_enable_x64", False)                        # another library switches it off
J = arm.jacobian(theta)
ik = arm.ik(arm.position(theta), restarts=2)
jax.config.update("jax_enable_x64", True)
reference = arm.jacobian(np.asarray(theta, dtype=np.float64))
assert J.dtype == np.float64, J.dtype
assert np.abs(np.asarray(J) - np.asarray(reference)).max() < 1e-14
assert ik.distance < 1e-9, ik.distance
print("ok")
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "ok" in proc.stdout, proc.stderr[-3000:]


# ---- errors -------------------------------------------------------------------------------------------------


def test_located_errors_with_suggestions(seed_model, seed_arm):
    with pytest.raises(UnknownNameError, match="no point or frame named 'hand.tpi'") as err:
        Kinematics(seed_model, "hand.tpi")
    assert "hand.tip" in str(err.value)
    with pytest.raises(KinematicsError, match="'neck.q1' does not move 'hand.tip'") as err:
        Kinematics(seed_model, "hand.tip", chain="neck.q1")
    assert "arm.q1" in str(err.value)
    with pytest.raises(UnknownNameError, match="'arm.q9'") as err:
        Kinematics(seed_model, "hand.tip", chain="arm.q1,arm.q9")
    assert "did you mean 'arm.q7'" in str(err.value)
    with pytest.raises(UnknownNameError, match="matches no parameter"):
        Kinematics(seed_model, "hand.tip", chain="leg.q*")
    with pytest.raises(KinematicsError, match="twice"):
        Kinematics(seed_model, "hand.tip", chain="arm.q1, arm.q*")
    with pytest.raises(KinematicsError, match="'world' does not move"):
        Kinematics(seed_model, "world")
    with pytest.raises(KinematicsError, match=r"shape \(6,\).*7 variables \(arm.q1"):
        seed_arm.position(np.zeros(6))
    with pytest.raises(KinematicsError, match="unknown frame 'base'"):
        seed_arm.jacobian(np.zeros(7), frame="base")
    with pytest.raises(KinematicsError, match="IK targets"):
        seed_arm.ik([1.0, 2.0])


def test_a_urdfs_own_joint_names_name_their_readings(urdf_model, tmp_path, write_model):
    """'--chain joint1,joint2' of a URDF said "did you mean 'joint1.z', 'joint1.y', 'joint1.x'?"."""
    assert Kinematics(urdf_model, "tool_center", chain="joint1,joint2").joints == ["joint1.q", "joint2.q"]
    assert Kinematics(urdf_model, "tool_center", chain=["joint3", "joint1.q"]).joints == ["joint3.q", "joint1.q"]
    with pytest.raises(UnknownNameError, match="'joint8', which is neither") as err:
        Kinematics(urdf_model, "tool_center", chain="joint1,joint8")
    assert "did you mean 'joint7.q'" in str(err.value)
    with pytest.raises(UnknownNameError, match="did you mean 'joint2.q'"):
        Kinematics(urdf_model, "tool_center", chain="jiont2")
    # a <mimic> joint has no reading: what it follows is said
    path = tmp_path / "mix.urdf"
    path.write_text(MIX, encoding="utf-8")
    for name in ("j3", "c"):  # the joint's name, its link's
        with pytest.raises(UnknownNameError, match=f"'{name}', a joint without a reading of its own") as err:
            Kinematics(mbcal.load_model(path), "d", what="frame", chain=name)
        assert "it follows j1.q" in str(err.value)
    # a frame whose joint reads p, beside a reading x.q of another joint: 'x' is ambiguous
    model = mbcal.load_model(
        write_model(
            "param p = 0 deg per configuration\nparam x.q = 0 deg per configuration\n"
            "object x at (0, 0, 0) {\n  joint revolute(z, p)\n  object y at (0.1 m, 0, 0) {\n"
            "    joint revolute(z, x.q)\n    point tip = (0.1 m, 0, 0)\n  }\n}\n"
        )
    )
    with pytest.raises(UnknownNameError, match="'x' is ambiguous.*p.*x.q"):
        Kinematics(model, "tip", chain="x")
    assert Kinematics(model, "tip", chain="y").joints == ["x.q"]


# ---- the command --------------------------------------------------------------------------------------------


def test_the_command_prints_f_j_and_j_star(capsys):
    code = main(
        ["kinematics", str(MODELS / "arm7.mdl"), "--chain", "arm.q*", "--point", "hand.tip",
         "--joints", "10deg,-30deg,0,-60deg,0,20deg,0"]
    )  # fmt: skip
    out = capsys.readouterr().out
    assert code == 0
    for text in ("hand.tip of", "f(θ): position", "J (world axes", "J* = Jᵀ(JJᵀ)⁻¹ of the position rows", "arm.q7"):
        assert text in out, text


def test_the_command_refuses_set_of_a_chain_variable_beside_joints(capsys):
    """'--set arm.q1=5deg' with '--joints' was dropped in silence (θ came from --joints)."""
    argv = ["kinematics", str(MODELS / "arm7.mdl"), "--point", "hand.tip", "--chain", "arm.q1,arm.q2"]
    assert main([*argv, "--joints=-30deg,20deg", "--set", "arm.q1=5deg"]) == 2
    assert "--set arm.q1 gives the chain variable arm.q1, which --joints gives too" in capsys.readouterr().err
    # without --joints the chain starts at the --set value; other parameters are held as given
    assert main([*argv, "--set", "arm.q1=5deg", "--json", "-", "-q"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [row["value"] for row in data["chain"]] == pytest.approx([np.radians(5.0), 0.0])
    assert main([*argv, "--joints=-30deg,20deg", "--set", "arm.offset4=2deg", "-q"]) == 0


@pytest.mark.slow
def test_the_command_solves_ik_and_writes_json(capsys):
    q = np.radians([10, -30, 0, -60, 0, 20, 0])
    arm = Kinematics(mbcal.load_model(MODELS / "arm7.mdl"), "hand.tip", chain="arm.q*")
    target = ",".join(f"{v:.12f}" for v in np.asarray(arm.position(q)))
    code = main(
        ["kinematics", str(MODELS / "arm7.mdl"), "--chain", "arm.q*", "--point", "hand.tip", "--ik", target,
         "--joints", "5deg,-20deg,0,-50deg,0,10deg,0", "--json", "-", "--axes", "local", "--part", "full"]
    )  # fmt: skip
    captured = capsys.readouterr()
    data = json.loads(captured.out)
    assert code == 0 and "reached" in captured.err
    assert data["jacobian"]["frame"] == "local" and len(data["pseudo_inverse"]["matrix"]) == 7
    assert len(data["pseudo_inverse"]["columns"]) == 6
    assert data["ik"]["targets"][0]["reached"] and data["ik"]["targets"][0]["distance"] < 1e-9


@pytest.mark.slow
def test_the_command_exit_status_for_unreachable_singular_and_bad_input(capsys):
    arm = str(MODELS / "arm7.mdl")
    assert main(["kinematics", arm, "--chain", "arm.q*", "--point", "hand.tip", "--ik", "2,0,1", "-q"]) == 1
    assert main(["kinematics", arm, "--chain", "arm.q*", "--point", "hand.tip", "-q"]) == 1  # straight: singular
    assert main(["kinematics", arm, "--chain", "arm.q*", "--point", "hand.tip", "--joints", "0,0"]) == 2
    assert main(["kinematics", arm, "--point", "hand.tip", "--joints", "0,x,0"]) == 2
    assert main(["kinematics", arm, "--point", "hand.tpi"]) == 2
    err = capsys.readouterr().err
    assert "--joints gives 2 values, but the chain has 7" in err
    assert "'x' is not a number" in err and "did you mean 'hand.tip'" in err
    urdf = str(URDF)
    assert main(["kinematics", urdf, "--point", "tool_center", "--joints", "0.1,0.2,0.3,-0.4,0.5,0.6,0.7", "-q"]) == 0
    # joint1 past 166°, joint4 past 28.6°: said and exit 1 (a table of f(θ) and J at a configuration
    # the robot cannot take was printed without a word, exit 0)
    capsys.readouterr()
    assert main(["kinematics", urdf, "--point", "tool_center", "--joints", "3,0,0,1,0,0,0", "--json", "-"]) == 1
    out = capsys.readouterr().out
    assert json.loads(out[out.index("{") :])["outside_limits"] == ["joint1.q", "joint4.q"]
