"""Range data in: readers round-trip, malformed files give located errors (exit 2), the depth
camera in the language, the edge rule, voxels, and `mbcal fit` on a point cloud."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

import mbcal
from mbcal.cli import main
from mbcal.errors import MbcalError, MeasurementFileError
from mbcal.range.readers import read_cloud, read_depth, write_depth_png, write_pcd, write_ply, write_xyz
from mbcal.range.scans import Scan, depth_to_points, edge_mask, load_scan, voxel_downsample

from conftest import MEASUREMENTS, MODELS

ROOM = str(MODELS / "room_depth.mdl")


@pytest.fixture
def cloud():
    return np.random.default_rng(1).uniform(-2, 2, (257, 3))


# ---- round trips ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", ["ply", "pcd", "pcd-ascii", "xyz", "csv", "npy", "obj"])
def test_cloud_round_trip(tmp_path, cloud, suffix):
    if suffix == "ply":
        path = tmp_path / "c.ply"
        write_ply(path, cloud)
        tol = 1e-6
    elif suffix.startswith("pcd"):
        path = tmp_path / "c.pcd"
        write_pcd(path, cloud, binary=suffix == "pcd")
        tol = 1e-6
    elif suffix in ("xyz", "csv"):
        path = tmp_path / f"c.{suffix}"
        write_xyz(path, cloud, "," if suffix == "csv" else " ")
        tol = 0
    elif suffix == "obj":
        path = tmp_path / "c.obj"
        path.write_text("# points\n" + "".join(f"v {x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in cloud))
        tol = 0
    else:
        path = tmp_path / "c.npy"
        np.save(path, cloud)
        tol = 0
    got = read_cloud(path)
    assert got.points.shape == cloud.shape
    np.testing.assert_allclose(got.points, cloud, atol=tol * 10, rtol=tol)


def test_pcd_with_extra_fields_and_nan(tmp_path):
    rows = np.zeros(3, dtype=[("rgb", "<f4"), ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<u2")])
    rows["x"], rows["y"], rows["z"] = [1, np.nan, 3], [4, 5, 6], [7, 8, 9]
    head = "VERSION 0.7\nFIELDS rgb x y z intensity\nSIZE 4 4 4 4 2\nTYPE F F F F U\nCOUNT 1 1 1 1 1\n"
    head += "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary\n"
    (tmp_path / "x.pcd").write_bytes(head.encode() + rows.tobytes())
    got = read_cloud(tmp_path / "x.pcd")
    assert got.dropped == 1
    np.testing.assert_allclose(got.points, [[1, 4, 7], [3, 6, 9]])


def test_depth_round_trip_png_tiff_npy(tmp_path):
    from PIL import Image

    depth = np.random.default_rng(0).uniform(0.5, 3.0, (6, 8))
    depth[2, 3] = np.nan
    write_depth_png(tmp_path / "d.png", depth)
    got = read_depth(tmp_path / "d.png")
    assert np.isnan(got[2, 3])
    np.testing.assert_allclose(got[np.isfinite(depth)], depth[np.isfinite(depth)], atol=0.5e-3)
    Image.fromarray(depth.astype(np.float32), mode="F").save(tmp_path / "d.tif")
    np.testing.assert_allclose(read_depth(tmp_path / "d.tif"), depth.astype(np.float32), equal_nan=True)
    np.save(tmp_path / "d.npy", depth)
    np.testing.assert_allclose(read_depth(tmp_path / "d.npy"), depth, equal_nan=True)


# ---- malformed files --------------------------------------------------------------------------------------


def _pcd_binary(n_claimed: int, n_written: int) -> bytes:
    head = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n_claimed}\nHEIGHT 1\nPOINTS {n_claimed}\nDATA binary\n"
    )
    return head.encode() + np.zeros((n_written, 3), dtype="<f4").tobytes()


MALFORMED = {
    "truncated.pcd": (_pcd_binary(100, 60), "truncated binary PCD"),
    "huge.pcd": (_pcd_binary(180_000_000, 2), "truncated binary PCD"),
    "claim.pcd": (_pcd_binary(500_000_000, 2), "more than mbcal reads"),
    "header.pcd": (b"VERSION 0.7\nFIELDZ x y z\nDATA ascii\n", "header.pcd:2:1: 'FIELDZ' is not a PCD header field"),
    "noxyz.pcd": (b"FIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2 3\n", "no 'x' field"),
    "ascii.pcd": (
        b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3\n1 two 3\n",
        "ascii.pcd:9:1: not a number",
    ),
    "lzf.pcd": (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA binary_compressed\n", "not supported"),
    "truncated.ply": (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + b"\0" * 120,
        "truncated",
    ),
    "huge.ply": (
        b"ply\nformat binary_little_endian 1.0\nelement vertex 178956970\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n" + b"\0" * 12,
        "truncated",
    ),
    "wrong.ply": (b"plx\nformat ascii 1.0\n", "wrong.ply:1:1: not a PLY file"),
    "bad.xyz": (b"1 2 3\n4 5\n", "bad.xyz:2:1: expected at least 3 numbers"),
    "text.csv": (b"x,y,z\n1,2,3\n1,2,zz\n", "text.csv:3:1: not a number"),
    "huge.npy": (b"", "truncated"),
    "depth_nan.tif": (b"", "no valid pixel"),
    "depth_neg.npy": (b"", "negative depth"),
    "depth8.png": (b"", "not a depth image"),
}


def _make(tmp_path, name):
    from PIL import Image

    data, expected = MALFORMED[name]
    path = tmp_path / name
    if name == "huge.npy":
        # A valid .npy header that claims 2 GB of float64 points, followed by 96 bytes.
        hdr = "{'descr': '<f8', 'fortran_order': False, 'shape': (90000000, 3), }".ljust(117) + "\n"
        path.write_bytes(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(hdr)) + hdr.encode() + bytes(96))
    elif name == "depth_nan.tif":
        Image.fromarray(np.full((4, 5), np.nan, dtype=np.float32), mode="F").save(path)
    elif name == "depth_neg.npy":
        d = np.ones((4, 5))
        d[1, 2] = -1
        np.save(path, d)
    elif name == "depth8.png":
        Image.fromarray(np.zeros((4, 5), dtype=np.uint8)).save(path)
    else:
        path.write_bytes(data)
    return path, expected


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_files_give_located_errors(tmp_path, name):
    path, expected = _make(tmp_path, name)
    reader = read_depth if name.startswith("depth") else read_cloud
    with pytest.raises(MeasurementFileError) as err:
        reader(path)
    assert expected in str(err.value)
    assert str(path.name) in str(err.value)


@pytest.mark.parametrize("name", ["truncated.pcd", "claim.pcd", "header.pcd", "huge.ply"])
def test_cli_fit_malformed_exit_2_no_traceback(tmp_path, name, capsys):
    path, expected = _make(tmp_path, name)
    code = main(["fit", ROOM, str(path), "--estimate", "room.*"])
    out = capsys.readouterr()
    assert code == 2
    assert expected in out.err and "Traceback" not in out.err + out.out


def test_cli_fit_malformed_subprocess(tmp_path):
    import subprocess
    import sys

    path, expected = _make(tmp_path, "truncated.pcd")
    run = subprocess.run(
        [sys.executable, "-m", "mbcal", "fit", ROOM, str(path), "--estimate", "room.*"], capture_output=True, text=True
    )
    assert run.returncode == 2
    assert expected in run.stderr and "Traceback" not in run.stderr


# ---- the depth camera in the language -----------------------------------------------------------------------


def test_depth_camera_statement():
    model = mbcal.load_model_text(
        "frame cam at translate(0, 0, 1 m) {\n"
        "  range kinect(width = 8, height = 6, fx = 5, fy = 6, cx = 3, cy = 2,\n"
        "               scale = 0.1 mm, min = 30 cm, max = 4 m)\n"
        "}\n"
    )
    r = model.ranges[0]
    assert r.is_depth_camera and (r.width, r.height) == (8, 6)
    assert r.intrinsics == (5.0, 6.0, 3.0, 2.0)
    assert r.depth_scale == pytest.approx(1e-4) and r.min_range == pytest.approx(0.3) and r.max_range == 4.0
    assert r.directions.shape == (48, 3)
    np.testing.assert_allclose(r.directions[2 * 8 + 3], [0, 0, 1])  # the principal point's ray
    assert not mbcal.load_model_text("range s(direction = (0, 0, 1))").ranges[0].is_depth_camera


@pytest.mark.parametrize(
    "args, message",
    [
        ("width = 8, f = 5", "needs 'height'"),
        ("width = 8, height = 6", "needs a focal length"),
        ("width = 8, height = 6, f = 5, fx = 0", "takes f = ... or fx = ..., fy = ..., not both"),
        ("width = 8, height = 6, fx = 0, fy = 5", "the focal length fx must be positive, got 0"),
        ("width = 8, height = 6, fy = 5", "has fy but no fx"),
        ("width = 8.5, height = 6, f = 5", "whole number"),
        ("width = 8, height = 6, f = 5, fov = (1 deg, 1 deg)", "drop 'fov'"),
        ("width = 8, height = 6, f = 5, scale = 0 mm", "depth scale must be positive"),
        ("width = 8, height = 6, f = 5, min = 5 m, max = 4 m", "0 <= min < max"),
        ("direction = (0, 0, 1), scale = 1 mm", "depth camera's setting"),
    ],
)
def test_depth_camera_errors_are_located(args, message):
    with pytest.raises(MbcalError) as err:
        mbcal.load_model_text(f"range kinect({args})")
    assert message in str(err.value)
    assert ":1:" in str(err.value)


# ---- depth to points, edges and voxels ----------------------------------------------------------------------


def test_depth_to_points_and_edge_rule():
    model = mbcal.load_model_text("range cam(width = 9, height = 7, f = 10, min = 0.2 m, max = 5 m)")
    info = model.ranges[0]
    depth = np.full((7, 9), 2.0)
    depth[:, 5:] = 3.0  # a step: pixels beside it are edge pixels
    depth[0, 0] = np.nan
    ok = edge_mask(depth)
    assert not ok[3, 4] and not ok[3, 5] and ok[3, 2] and ok[3, 7]
    pts, pix, dropped = depth_to_points(depth, info)
    assert len(pts) == ok.sum() and dropped == np.isfinite(depth).sum() - ok.sum()
    r, c = pix[0]
    np.testing.assert_allclose(pts[0], [(c - 4) / 10 * depth[r, c], (r - 3) / 10 * depth[r, c], depth[r, c]])
    pts_all, _, _ = depth_to_points(depth, info, edge=None)
    assert len(pts_all) == np.isfinite(depth).sum()


def test_voxel_downsample():
    pts = np.array([[0.002, 0.0015, 0.001], [0.001, 0.001, 0.001], [0.004, 0.002, 0.001], [0.5, 0.5, 0.5]])
    out = voxel_downsample(pts, 0.01)
    assert len(out) == 2  # one measured point per voxel: the first in the scan's order
    np.testing.assert_allclose(out, pts[[0, 3]])


def test_load_scan_depth_image_needs_depth_camera(tmp_path):
    write_depth_png(tmp_path / "d.png", np.ones((4, 4)))
    model = mbcal.load_model(MODELS / "teleexistence.mdl")
    with pytest.raises(MeasurementFileError, match="depth camera"):
        load_scan(tmp_path / "d.png", model)
    with pytest.raises(MeasurementFileError, match="212 × 120"):
        load_scan(tmp_path / "d.png", mbcal.load_model(ROOM))


# ---- mbcal fit on a point cloud sampled from the room -------------------------------------------------------


def _room_cloud(model, truth, n=6000, seed=0, noise=1e-3):
    """Points on the room's shapes near the fittings at ``truth``, with noise and 5 % clutter."""
    import trimesh

    scene = mbcal.modeler(model, truth).to_trimesh(plane_size=3.0)
    mesh = trimesh.util.concatenate(list(scene.dump()))
    pts, _ = trimesh.sample.sample_surface(mesh, 4 * n, seed=seed)
    pts = pts[(np.abs(pts[:, 0]) < 0.6) & (pts[:, 1] > 0.4) & (pts[:, 2] > 0.7)][:n]
    rng = np.random.default_rng(seed)
    pts = pts + rng.normal(0, noise, pts.shape)
    clutter = rng.uniform([-0.5, 0.3, 0.9], [0.5, 0.6, 1.3], (n // 20, 3))
    return np.vstack([pts, clutter])


@pytest.mark.slow
def test_cli_fit_point_cloud(tmp_path, capsys):
    model = mbcal.load_model(ROOM)
    truth = {"room.x": 0.02, "room.y": -0.01, "room.yaw": np.radians(1.5)}
    write_pcd(tmp_path / "scan.pcd", _room_cloud(model, truth))
    out = tmp_path / "out"
    code = main(
        ["fit", ROOM, str(tmp_path / "scan.pcd"), "--estimate", "room.*", "--sigma", "0.001", "--out", str(out)]
    )
    text = capsys.readouterr().out
    report = json.loads((out / "room_depth.fit.json").read_text())
    assert code == 0, text
    for k, v in truth.items():
        assert abs(report["values"][k] - v) < 4 * report["std"][k] + 1e-4
    assert report["outliers"]["count"] >= 250  # the clutter belongs to no modelled surface
    assert len(read_cloud(out / "room_depth.outliers.ply").points) == report["outliers"]["count"]
    calibrated = mbcal.load_model(out / "room_depth.calibrated.mdl")
    assert calibrated.param("room.x").nominal == pytest.approx(report["values"]["room.x"], abs=1e-6)


@pytest.mark.slow
def test_a_cloud_down_sampled_by_default_is_fitted_without_bias(tmp_path):
    """A depth image's points as a cloud (no pixel grid): one point per 1 cm cube, whose membership
    the noisy position decides, put room.yaw 4.8 σ off with a verdict of ok; a random subset as
    large puts every unknown within 2 σ (all points: 0.3 σ)."""
    from mbcal.range.fit import fit_scans, scan_world_points
    from mbcal.range.simulate import add_depth_noise, render_depth

    model = mbcal.load_model(ROOM)
    truth = {"room.x": 0.02, "room.y": -0.01, "room.yaw": np.radians(1.5)}
    write_depth_png(tmp_path / "depth.png", add_depth_noise(render_depth(model, truth), 1e-3, 1e-3, seed=0))
    cloud = Scan(scan_world_points(model, load_scan(tmp_path / "depth.png", model)))
    kept = cloud.downsampled(0.01)
    assert len(kept) == len(voxel_downsample(cloud.points, 0.01)) < len(cloud)
    assert len({tuple(p) for p in kept} - {tuple(p) for p in cloud.points}) == 0  # measured points, unchanged
    fit = fit_scans(model, [cloud], ["room.*"])
    assert fit.ok, fit.text()
    for name, value in fit.values.items():
        assert abs(value - truth.get(name, 0.0)) < 2 * fit.std[name], (name, value, fit.std[name])


@pytest.mark.slow
def test_mixed_image_and_range():
    """Clicked image points and depth-image points in one problem: the room's pose from both."""
    from mbcal.measurements.sets import measurements_from_records, merge_measurements
    from mbcal.range.scans import depth_camera
    from mbcal.range.simulate import add_depth_noise, render_depth
    from mbcal.solver import SolverConfig

    model = mbcal.load_model(ROOM)
    truth = {"room.x": 0.012, "room.y": -0.01, "room.z": 0.006, "room.yaw": np.radians(1.2)}
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", model)
    images = mbcal.simulate(model, plan.subset([i < 12 for i in range(len(plan))]), truth, seed=1)
    info = depth_camera(model)
    pts, _, _ = depth_to_points(add_depth_noise(render_depth(model, truth), 2e-3, seed=2), info)
    pts = pts[::12]  # a subset chosen by pixel, not by the noisy position (see docs/range.md, voxels)
    frame = model.frames[info.frame].name
    records = [
        {"kind": "point_to_surface", "object": "room", "frame": frame, "x": x, "y": y, "z": z, "sigma": 0.002}
        for x, y, z in pts
    ]
    scans = measurements_from_records(records, model)
    both = mbcal.calibrate(
        model, merge_measurements([images, scans]), ["room.*"], restarts=4, config=SolverConfig(loss="cauchy")
    )
    alone = mbcal.calibrate(model, images, ["room.*"], restarts=4)
    assert both.ok, both.verdict.text() if hasattr(both.verdict, "text") else both
    for name in ("room.x", "room.y", "room.z", "room.yaw"):
        assert abs(both.values[name] - truth[name]) < 3 * both.std[name] + 1e-5, name
        assert both.std[name] < alone.std[name]  # the scan adds information to the clicks
    kinds = {r.kind for r in both.residuals}
    assert kinds == {"image_point", "point_to_surface"}


@pytest.mark.slow
def test_scan_residual_jacobian_matches_finite_differences():
    """The point-to-surface residual's autodiff Jacobian against central differences, with points
    near every shape kind of the room (tube, cylinder, box, sphere, cone, rectangle, plane, mesh)."""
    from mbcal._jax import jax, jnp
    from mbcal.params import ParameterSet
    from mbcal.range.fit import _engine, _Points, _prior_rows, residuals_at

    model = mbcal.load_model(ROOM)
    ps = ParameterSet(model, ["room.*", "lever.angle", "lever.length"])
    eng = _engine(model, ps, ((0, -1),))
    scene = mbcal.modeler(model, {})
    rng = np.random.default_rng(0)
    centres = np.asarray(scene.shape_poses)[:, :3, 3]
    pts = np.repeat(centres, 3, axis=0) + rng.normal(0, 0.03, (3 * len(centres), 3))
    kinds = {s.kind for s in model.shapes}
    assert {"tube", "cylinder", "box", "sphere", "cone", "rectangle", "plane", "mesh"} <= kinds
    x = ps.x0 + rng.normal(0, 1e-3, ps.size)
    cloud = _Points(eng, ps.known, pts, np.zeros(len(pts), dtype=np.int64))
    D, _ = cloud.screen(x, 0.02)
    cand, groups = cloud.groups(D, 0.02)
    assert cand.sum(axis=0)[[s.kind == "mesh" for s in model.shapes]].min() > 0  # the mesh is a candidate
    weight = np.r_[np.full(len(pts), 500.0), np.zeros(cloud.m - len(pts))]
    args = [weight, ps.known, *_prior_rows(ps, None, True), *groups]
    args = [cloud.P, cloud.Q, *(jnp.asarray(a) for a in args)]

    compiled = jax.jit(eng.residual)

    def residual(xx):
        return np.asarray(compiled(jnp.asarray(xx), *args))[: len(pts)]

    # At x, the residual over each point's candidate shapes is its distance to the nearest shape of all.
    values = dict(zip(ps.names, x))
    full = residuals_at(model, Scan(pts), values)
    np.testing.assert_allclose(residual(x), 500.0 * full, rtol=1e-9, atol=1e-9)
    J = np.asarray(eng.jacobian(jnp.asarray(x), *args))[: len(pts)]
    h = 1e-6
    for j in range(ps.size):
        e = np.zeros(ps.size)
        e[j] = h
        np.testing.assert_allclose(J[:, j], (residual(x + e) - residual(x - e)) / (2 * h), rtol=1e-4, atol=1e-4 * 500)
    assert np.abs(J).max() > 1.0  # the residual does depend on the unknowns


SPHERE_SPIN = """param ball.x = 0 m in [-0.1 m, 0.1 m]
param ball.spin = 0 deg in [-10 deg, 10 deg]
object ball at (ball.x, 0, 1 m) * rot_z(ball.spin) {
  shape s = sphere(10 cm)
}
"""


def test_a_scan_fit_with_an_undetermined_unknown_writes_strict_json_and_exits_1(tmp_path, capsys):
    """A sphere's spin about its axis moves none of its surface: its σ is ∞.  `mbcal fit --json`
    raised ValueError on it (JSON has no ∞) and MODEL.fit.json held `Infinity`; now σ is null there,
    the text says unobservable, and the exit status is 1."""
    model = tmp_path / "ball.mdl"
    model.write_text(SPHERE_SPIN)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    write_xyz(tmp_path / "ball.xyz", d * 0.1 + np.array([0.01, 0.0, 1.0]))
    out = tmp_path / "out"
    argv = ["fit", str(model), str(tmp_path / "ball.xyz"), "--estimate", "ball.*", "--sigma", "0.001"]

    def strict(text):
        def refuse(token):
            raise AssertionError(f"{token} is not JSON")

        return json.loads(text, parse_constant=refuse)

    assert main([*argv, "--json", "-", "--out", str(out)]) == 1
    captured = capsys.readouterr()
    report = strict(captured.out)
    assert report["std"]["ball.spin"] is None and report["std"]["ball.x"] > 0 and not report["ok"]
    assert report["unobservable"] and "ball.spin" in report["unobservable"][0]
    assert abs(report["values"]["ball.x"] - 0.01) < 4 * report["std"]["ball.x"]
    assert strict((out / "ball.fit.json").read_text())["std"] == report["std"]
    assert "∞ (unobservable)" in captured.err and "NOT trustworthy" in captured.err


def test_a_scan_leaves_out_points_that_are_not_finite_as_the_readers_do():
    """A Scan made in Python with some NaN coordinates lost ~99 % of its valid points in the voxel
    down-sampling (NaN in the voxel keys) and the fit said ok."""
    from mbcal.range.scans import Scan

    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (1000, 3))
    pts[::10, 2] = np.nan
    scan = Scan(pts)
    assert len(scan) == 900 and scan.dropped == 100 and "100 point(s)" in scan.notes[-1]
    assert len(scan.downsampled(0.05)) > 500  # most of the valid points survive down-sampling
    with pytest.raises(MbcalError, match="no point has finite coordinates"):
        Scan(np.full((5, 3), np.nan))
