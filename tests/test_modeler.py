"""modeler(D, X): positions against hand-computed transforms; autodiff against finite differences."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from mbcal.language import load_model, load_model_text
from mbcal.modeling import modeler
from mbcal.params import ParameterSet

from conftest import MODELS


def Rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def Ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def Rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def T(R=None, t=(0, 0, 0)):
    M = np.eye(4)
    M[:3, :3] = np.eye(3) if R is None else R
    M[:3, 3] = t
    return M


def test_nested_frames_compose_translations_rotations_and_joints():
    text = """
    param base.yaw = 20 deg
    param q = 35 deg
    param off = -5 deg
    param slide = 7 cm
    frame base at translate(1 m, 2 m, 0.5 m) * rot_z(base.yaw) {
      object arm at translate(0.3 m, 0, 0) * rpy(10 deg, -20 deg, 30 deg) {
        joint revolute(y, q, offset = off)
        point tip = (0.5 m, 0, 0)
        object slider at axis_angle((1, 1, 0), 40 deg) {
          joint prismatic(z, slide)
          point end = (0, 0.1 m, 0)
        }
      }
    }
    """
    model = load_model_text(text)
    scene = modeler(model, model.nominal)
    d = math.radians
    T_base = T(Rz(d(20)), (1, 2, 0.5))
    T_arm = T_base @ T(Rz(d(30)) @ Ry(d(-20)) @ Rx(d(10)), (0.3, 0, 0)) @ T(Ry(d(30)))
    axis = np.array([1, 1, 0]) / math.sqrt(2)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_aa = np.eye(3) + math.sin(d(40)) * K + (1 - math.cos(d(40))) * K @ K
    T_slider = T_arm @ T(R_aa) @ T(t=(0, 0, 0.07))
    np.testing.assert_allclose(np.asarray(scene.frame("base.arm")), T_arm, atol=1e-12)
    np.testing.assert_allclose(np.asarray(scene.point("base.arm.tip")), (T_arm @ [0.5, 0, 0, 1])[:3], atol=1e-12)
    np.testing.assert_allclose(np.asarray(scene.point("slider.end")), (T_slider @ [0, 0.1, 0, 1])[:3], atol=1e-12)


def test_quaternion_pose_and_look_at():
    text = """
    frame q at quat(cos(15 deg), 0, 0, sin(15 deg))            # 30 deg about z
    frame p at pose(1 m, 2 m, 3 m, 0, 0, 90 deg)
    frame cam at look_at(eye = (0, 0, 1 m), target = (0, 5 m, 1 m))
    """
    scene = modeler(load_model_text(text), np.zeros(0))
    np.testing.assert_allclose(np.asarray(scene.frame("q"))[:3, :3], Rz(math.radians(30)), atol=1e-12)
    np.testing.assert_allclose(np.asarray(scene.frame("p")), T(Rz(math.pi / 2), (1, 2, 3)), atol=1e-12)
    cam = np.asarray(scene.frame("cam"))
    # OpenCV axes: optical axis (z) towards +y, image x to the right (+x), image y down (-z).
    np.testing.assert_allclose(cam[:3, :3], [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)


def test_camera_projects_like_the_pinhole_formula():
    text = """
    camera c(width = 640, height = 480, fx = 500, fy = 520, cx = 320, cy = 240, skew = 0.5,
             k1 = -0.1, k2 = 0.01, p1 = 0.001, p2 = -0.002, k3 = 0.001)
    point p = (0.2 m, -0.1 m, 2 m)
    """
    scene = modeler(load_model_text(text), np.zeros(0))
    x, y = 0.1, -0.05
    r2 = x * x + y * y
    radial = 1 - 0.1 * r2 + 0.01 * r2**2 + 0.001 * r2**3
    xd = x * radial + 2 * 0.001 * x * y - 0.002 * (r2 + 2 * x * x)
    yd = y * radial + 0.001 * (r2 + 2 * y * y) + 2 * -0.002 * x * y
    expected = [500 * xd + 0.5 * yd + 320, 520 * yd + 240]
    np.testing.assert_allclose(np.asarray(scene.camera("c").project(scene.point("p"))), expected, rtol=1e-12)


def test_camera_projection_matches_opencv():
    import cv2

    text = """
    camera c(width = 640, height = 480, fx = 500, fy = 520, cx = 320, cy = 240,
             k1 = -0.1, k2 = 0.01, p1 = 0.001, p2 = -0.002, k3 = 0.001) at rpy(5 deg, -3 deg, 10 deg) * (0.1, 0, 0)
    """
    model = load_model_text(text)
    scene = modeler(model, np.zeros(0))
    cam = scene.camera("c")
    rng = np.random.default_rng(0)
    world = rng.uniform([-0.5, -0.4, 1.5], [0.5, 0.4, 3.0], size=(20, 3))
    ours = np.asarray(cam.project(world))
    T_cw = np.linalg.inv(np.asarray(cam.T_world_camera))
    rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
    dist = np.asarray(cam.distortion)
    theirs, _ = cv2.projectPoints(world, rvec, T_cw[:3, 3], cam.K, dist)
    np.testing.assert_allclose(ours, theirs[:, 0, :], atol=1e-9)


@pytest.mark.parametrize("model_name", ["teleexistence.mdl", "arm7.mdl"])
def test_jacfwd_through_the_modeler_matches_finite_differences(model_name):
    model = load_model(MODELS / model_name)
    X0 = model.nominal + np.random.default_rng(1).normal(0, 0.05, len(model.params))

    def f(X):
        scene = modeler(model, X)
        return jax.numpy.concatenate([scene.points.ravel(), scene.frame_poses.ravel(), scene.shape_dims.ravel()])

    J = np.asarray(jax.jit(jax.jacfwd(f))(X0))
    h = 1e-6
    fd = np.stack([(np.asarray(f(X0 + h * e)) - np.asarray(f(X0 - h * e))) / (2 * h) for e in np.eye(len(X0))], 1)
    np.testing.assert_allclose(J, fd, atol=1e-7)
    assert np.abs(J).max() > 0.1  # the parameters do move things


def test_modeler_is_jittable_and_vmaps_over_configurations():
    model = load_model(MODELS / "arm7.mdl")
    configs = [f"pose{i}" for i in range(4)]
    readings = {c: {f"arm.q{j}": 0.1 * i * j for j in range(1, 8)} for i, c in enumerate(configs)}
    ps = ParameterSet(model, ["arm.offset*"], configurations=configs, per_configuration=readings)
    x = np.linspace(-0.05, 0.05, 7)
    X = ps.param(x)
    tips = jax.jit(jax.vmap(lambda Xc: modeler(model, Xc).point("hand.tip")))(X)
    for i in range(4):
        direct = modeler(model, np.asarray(X[i])).point("hand.tip")
        np.testing.assert_allclose(np.asarray(tips[i]), np.asarray(direct), atol=1e-12)
    assert not np.allclose(np.asarray(tips[0]), np.asarray(tips[1]))


def test_joint_offset_adds_to_the_reading():
    model = load_model_text(
        "param q = 10 deg\nparam off = 5 deg\nframe f { joint revolute(z, q, offset = off)\n point p = (1 m, 0, 0) }"
    )
    p = np.asarray(modeler(model, model.nominal).point("f.p"))
    np.testing.assert_allclose(p, [math.cos(math.radians(15)), math.sin(math.radians(15)), 0], atol=1e-12)


def test_scene_exports_to_trimesh_with_every_shape():
    model = load_model(MODELS / "teleexistence.mdl")
    tm = modeler(model, model.nominal).to_trimesh()
    assert len(tm.geometry) == len(model.shapes)
    lever = tm.geometry["room.valve.lever.arm"]
    assert lever.is_watertight
    assert tm.bounds[1][2] > 1.28  # the upper pipe is at 1.3 m
