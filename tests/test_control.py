"""Impedance control (seed eqs. 1–4, 7): the contact models, the master–slave loop against a wall,
and the seed's lever task (section 4.3) as seeded facts about the simulation."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mbcal
from mbcal.control import (
    Box,
    Cylinder,
    Environment,
    HalfSpace,
    Impedance,
    follow_path,
    lever_from_model,
    min_jerk,
    simulate,
    surfaces_from_model,
)
from mbcal.errors import KinematicsError
from mbcal.kinematics import Kinematics
from mbcal.workflows.demo import DEMO_TRUTH

from conftest import MODELS

READY = np.radians([-40, 0, 0, -90, 0, 0, 0])
FORWARDS = np.array([1.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def arm():
    return Kinematics(mbcal.load_model(MODELS / "arm7.mdl"), "hand.tip", chain="arm.q*")


@pytest.fixture(scope="module")
def push(arm):
    """The master moves the hand 10 cm forwards in 1 s and holds 4 s (dt = 1 ms)."""
    start = np.asarray(arm.position(READY))
    path = min_jerk(start, start + 0.10 * FORWARDS, np.linspace(0.0, 1.0, 1000))
    path = np.concatenate([path, np.repeat(path[-1:], 4000, axis=0)])
    return start, path, follow_path(arm, path, READY)


def test_the_seeds_impedance_is_the_default_and_is_checked():
    M, B, K = Impedance().matrices()
    np.testing.assert_array_equal(M, 6 * np.eye(3))
    np.testing.assert_array_equal(B, 100 * np.eye(3))
    np.testing.assert_array_equal(K, 50 * np.eye(3))
    np.testing.assert_array_equal(Impedance(K=[10, 20, 30]).matrices()[2], np.diag([10.0, 20.0, 30.0]))
    with pytest.raises(KinematicsError, match="M must be positive definite"):
        Impedance(M=0.0).matrices()
    with pytest.raises(KinematicsError, match="K must be symmetric"):
        Impedance(K=[[1, 2, 0], [0, 1, 0], [0, 0, 1]]).matrices()


def test_the_master_path_is_followed(arm, push):
    _, path, theta = push
    assert theta.shape == (len(path), 7)
    assert np.abs(np.asarray(arm.position(theta)) - path).max() < 1e-6


def test_without_contact_the_slave_copies_the_master(arm, push):
    _, _, theta = push
    run = simulate(arm, theta[:1500], Environment(), impedance=Impedance())
    assert np.abs(run.e).max() == 0.0 and np.abs(run.force).max() == 0.0
    np.testing.assert_allclose(run.x_slave, run.x_master, atol=1e-15)
    assert np.isnan(run.lever_angle).all() and not run.held and run.grasp_step == -1


def test_against_a_wall_impedance_yields_and_position_control_presses(arm, push):
    start, _, theta = push
    radius = 0.04
    wall = HalfSpace(point=tuple(start + (0.05 + radius) * FORWARDS), normal=(-1.0, 0.0, 0.0))
    room = Environment(surfaces=(wall,))
    soft = simulate(arm, theta, room, dt=1e-3, impedance=Impedance())
    stiff = simulate(arm, theta, room, dt=1e-3)
    # Position control: the wall's 20,000 N/m times the 5 cm the hand is driven in.
    assert stiff.force[-1, 0] == pytest.approx(-1000.0, rel=1e-3)
    # Impedance control stops the hand at the wall (0.1 mm in) and settles where K e balances the
    # wall's force; e is 4.6 cm, not the 5 cm the hand stays behind, because θ_s = θ_m + J* e moves
    # the hand by e only to first order (eq. 7 linearises at the master's θ).
    assert soft.force[-1, 0] == pytest.approx(50.0 * soft.e[-1, 0], rel=1e-6)
    assert -0.05 < soft.e[-1, 0] < -0.04
    assert soft.x_slave[-1, 0] - start[0] == pytest.approx(0.05, abs=5e-4)
    np.testing.assert_allclose(soft.force[-1000:], soft.force[-1:].repeat(1000, axis=0), atol=1e-6)  # settled
    # The impact of the 6 kg target inertia is the largest force: bounded, far below position control's.
    assert 20.0 < soft.peak_force < 100.0 < stiff.peak_force


def _floor_under_straight_arm(arm, depth=0.01):
    """The arm hanging straight (arm7's nominal pose: singular, J loses a row) with a floor the
    master's hand is ``depth`` into."""
    hand = np.asarray(arm.position(np.zeros(7)))
    floor = HalfSpace(point=(0.0, 0.0, hand[2] - 0.04 + depth), normal=(0.0, 0.0, 1.0))
    return Environment(surfaces=(floor,))


def test_a_singular_master_without_damping_is_refused_not_nan(arm):
    # J* = Jᵀ(JJᵀ)⁻¹ is NaN there: the slave's joints and hand were NaN, the NaN hand touched
    # nothing and the force read 0 N although the master pushes 1 cm into the floor.
    floor = _floor_under_straight_arm(arm)
    for env in (floor, Environment()):
        with pytest.raises(KinematicsError, match=r"J\* = Jᵀ\(JJᵀ\)⁻¹ is not finite at step 0 \(t = 0 s\)") as info:
            simulate(arm, np.zeros((200, 7)), env, impedance=Impedance())
        text = str(info.value)
        assert "arm.q1 0 deg" in text and "arm.q7 0 deg" in text and "singular" in text
        assert "damping=1e-2" in text and "away from the singularity" in text
    # Reaching the singularity later: the first step where J* is not finite is named.
    theta = np.linspace(np.radians([0, 0, 0, -30, 0, 0, 0]), np.zeros(7), 50)
    with pytest.raises(KinematicsError, match=r"step 49 \(t = 0\.049 s\)"):
        simulate(arm, theta, floor, impedance=Impedance())
    # A damping too small to help says so.
    with pytest.raises(KinematicsError, match="larger damping than λ = 1e-09"):
        simulate(arm, np.zeros((20, 7)), floor, impedance=Impedance(), damping=1e-9)
    # Position control does not use J*: it runs and presses with the floor's stiffness.
    assert simulate(arm, np.zeros((20, 7)), floor).force[-1, 2] == pytest.approx(200.0)


def test_a_singular_master_with_damping_runs_and_feels_the_floor(arm):
    run = simulate(arm, np.zeros((200, 7)), _floor_under_straight_arm(arm), impedance=Impedance(), damping=1e-2)
    for a in (run.theta_slave, run.x_slave, run.e, run.force):
        assert np.all(np.isfinite(a))
    # The straight arm cannot give way along itself (J has no z row to damp): the hand stays 1 cm
    # in and the floor pushes back with its 20,000 N/m, as under position control.
    assert run.force[-1, 2] == pytest.approx(200.0, rel=1e-3) and run.peak_force > 100.0
    assert run.e[-1, 2] > 0.0


def test_the_master_trajectory_and_damping_are_checked(arm):
    theta = np.zeros((10, 7))
    theta[3, 2] = np.nan
    with pytest.raises(KinematicsError, match=r"master trajectory is not finite at step 3 .*arm\.q3 nan"):
        simulate(arm, theta, Environment(), impedance=Impedance(), damping=1e-2)
    with pytest.raises(KinematicsError, match="damping λ of J\\* must be finite and ≥ 0"):
        simulate(arm, np.zeros((10, 7)), Environment(), impedance=Impedance(), damping=-1.0)


def test_the_lever_follows_the_model():
    model = mbcal.load_model(MODELS / "teleexistence.mdl")
    for values in ({}, DEMO_TRUTH):
        lever = lever_from_model(model, "room.valve.lever", "lever.angle", dict(values), grip=(0.0, -0.02, 0.25))
        assert lever.angle == pytest.approx(math.radians(20.0)) and lever.rest == lever.angle
        assert lever.length == pytest.approx(math.hypot(0.25, 0.0), abs=1e-12)
        for degrees in (-30.0, 20.0, 75.0):
            scene = mbcal.modeler(model, {**values, "lever.angle": math.radians(degrees)})
            expected = np.asarray(scene.point("lever.knob_front"))
            np.testing.assert_allclose(np.asarray(lever.grip(math.radians(degrees))), expected, atol=1e-12)
    with pytest.raises(KinematicsError, match="does not move"):
        lever_from_model(model, "room.valve.lever", "fan.angle")


def test_hard_surfaces_from_the_room():
    model = mbcal.load_model(MODELS / "teleexistence.mdl")
    surfaces = surfaces_from_model(model, exclude=["room.valve.lever"], free_point=(0.0, 0.0, 1.0))
    names = {s.name: s for s in surfaces}
    assert "lever.arm" not in names and "lever.knob" not in names
    wall, floor = names["room.wall"], names["room.floor"]
    assert isinstance(wall, HalfSpace) and np.allclose(wall.normal, (0, -1, 0), atol=1e-12)
    assert isinstance(floor, HalfSpace) and np.allclose(floor.normal, (0, 0, 1), atol=1e-12)
    assert isinstance(names["box.housing"], Box) and isinstance(names["lower_pipe.shape0"], Cylinder)
    box = names["box.housing"]
    assert float(box.distance(np.asarray(box.centre))) == pytest.approx(-0.05)  # 10 cm deep: 5 cm to the front
    pipe = names["lower_pipe.shape0"]
    assert float(pipe.distance(np.asarray(pipe.centre) + np.array([0.0, 0.0, 0.1]))) == pytest.approx(0.1 - 0.02415)


@pytest.mark.slow
def test_the_seeds_lever_task():
    """Seeded facts of the simulation (docs/control.md has the full results): the uncalibrated
    model misses, the calibrated one pulls the lever under impedance control with forces of a few
    newtons, and with the seed's residual error along the line of sight position control presses
    with the closed hand's stiffness while impedance control yields."""
    from mbcal.workflows.lever import LeverTask, calibrated_room, displaced, run_lever_task, seed_cases

    task = LeverTask()
    room = calibrated_room(restarts=8, seed=0)
    assert room["room.y"] == pytest.approx(DEMO_TRUTH["room.y"], abs=0.01)
    near = displaced(DEMO_TRUTH, 0.03)
    cases = run_lever_task(
        seed_cases(room) + [("3 cm, impedance", near, True), ("3 cm, position", near, False)], task=task
    )
    uncalibrated, calibrated, position, near_impedance, near_position = cases

    assert not uncalibrated.held and not uncalibrated.success
    assert (
        uncalibrated.grasp_distance > 0.15 and abs(uncalibrated.grasp_error[1]) > 0.15
    )  # short along the line of sight
    assert uncalibrated.final_angle == pytest.approx(math.radians(20.0), abs=1e-9)
    assert uncalibrated.peak_force == 0.0

    for case in (calibrated, position):
        assert case.held and case.pulled and case.success
        assert case.grasp_distance < 0.01
    assert calibrated.peak_pull_force < 5.0
    assert math.degrees(calibrated.final_angle) == pytest.approx(86.6, abs=1.0)  # K e lags the master
    assert math.degrees(position.final_angle) == pytest.approx(90.0, abs=0.5)  # against the stop

    assert near_impedance.success and near_position.success
    steady = slice(near_position.run.grasp_step + 500, near_position.run.grasp_step + 3000)
    held = np.linalg.norm(near_position.run.force[steady], axis=1)
    assert held.mean() == pytest.approx(task.grasp_stiffness * 0.03, rel=0.02)  # the whole 3 cm in the hand's spring
    assert np.linalg.norm(near_impedance.run.force[steady], axis=1).mean() < 5.0
    assert near_position.peak_pull_force > 3 * near_impedance.peak_pull_force
