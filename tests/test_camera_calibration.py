"""Camera calibration on real data (Zhang's) and on synthetic images with known truth."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import mbcal
from mbcal.workflows.cameras import (
    calibrate_cameras,
    homography,
    intrinsics_from_homographies,
    plan_views,
    pose_from_homography,
    simulate_views,
    synthesize_images,
    zhang_start,
)
from mbcal.workflows.detect import detect_images

from conftest import MODELS, shared_data

# Z. Zhang's published result with distortion (calibration-result-zhang-withdistortion.txt).
ZHANG = {"fx": 832.5, "skew": 0.204494, "fy": 832.53, "cx": 303.959, "cy": 206.585, "k1": -0.228601, "k2": 0.190353}


def zhang_model(target: str, *, skew: bool) -> mbcal.Model:
    folder = shared_data("zhang")
    skew_param = "param cam.skew = 0 in [-5, 5]\n" if skew else ""
    skew_arg = ", skew = cam.skew" if skew else ""
    text = f"""
    param cam.fx = 800 in [500, 1200]
    param cam.fy = 800 in [500, 1200]
    param cam.cx = 320 in [250, 390]
    param cam.cy = 240 in [180, 300]
    {skew_param}
    param cam.k1 = 0 in [-1, 1]
    param cam.k2 = 0 in [-1, 1]
    param plane.x = 0 m per configuration
    param plane.y = 0 m per configuration
    param plane.z = 0.3 m per configuration
    param plane.roll = 0 deg per configuration
    param plane.pitch = 0 deg per configuration
    param plane.yaw = 0 deg per configuration
    camera cam(width = 640, height = 480, fx = cam.fx, fy = cam.fy, cx = cam.cx, cy = cam.cy{skew_arg},
               k1 = cam.k1, k2 = cam.k2)
    target plane = {target.format(folder=folder)} at pose(plane.x, plane.y, plane.z, plane.roll, plane.pitch, plane.yaw)
    """
    return mbcal.load_model_text(text)


def zhang_corners(model) -> mbcal.MeasurementSet:
    folder = shared_data("zhang")
    records = []
    for view in range(1, 6):
        uv = np.loadtxt(folder / f"data{view}.txt").reshape(-1, 2)
        for k, (u, v) in enumerate(uv):
            records.append(
                {
                    "kind": "image_point",
                    "config": f"view{view}",
                    "camera": "cam",
                    "point": f"plane.p{k}",
                    "u": u,
                    "v": v,
                    "sigma": 0.5,
                }
            )
    return mbcal.measurements_from_records(records, model)


POINTS_FILE = 'points("{folder}/Model.txt", scale = 1 inch)'


@pytest.mark.slow
def test_zhangs_data_reproduces_his_published_calibration_with_skew():
    model = zhang_model(POINTS_FILE, skew=True)
    cc = calibrate_cameras(model, zhang_corners(model))
    assert cc.ok
    got = {k: v for k, (v, _) in cc.intrinsics["cam"].items()}
    for key in ("fx", "fy", "cx", "cy"):
        assert got[key] == pytest.approx(ZHANG[key], rel=1e-3), key
    assert got["skew"] == pytest.approx(ZHANG["skew"], abs=0.01)
    assert got["k1"] == pytest.approx(ZHANG["k1"], rel=1e-3)
    assert got["k2"] == pytest.approx(ZHANG["k2"], rel=1e-2)
    # His extrinsic translation of view 1, in inches.
    t1 = [cc.result.values[f"plane.{a}@view1"] / 0.0254 for a in "xyz"]
    np.testing.assert_allclose(t1, [-3.84019, 3.65164, 12.791], rtol=1e-3)


@pytest.mark.slow
def test_zhangs_data_matches_opencv_for_the_same_camera_model():
    import cv2

    folder = shared_data("zhang")
    model = zhang_model(POINTS_FILE, skew=False)
    cc = calibrate_cameras(model, zhang_corners(model))
    plane = np.loadtxt(folder / "Model.txt").reshape(-1, 2)
    obj = np.c_[plane, np.zeros(len(plane))].astype(np.float32)
    images = [np.loadtxt(folder / f"data{v}.txt").reshape(-1, 2).astype(np.float32) for v in range(1, 6)]
    flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-14)
    rms, K, dist, _, _ = cv2.calibrateCamera([obj] * 5, images, (640, 480), None, None, flags=flags, criteria=criteria)
    got = {k: v for k, (v, _) in cc.intrinsics["cam"].items()}
    for key, theirs in (("fx", K[0, 0]), ("fy", K[1, 1]), ("cx", K[0, 2]), ("cy", K[1, 2])):
        assert got[key] == pytest.approx(theirs, rel=1e-3), key
    assert abs(cc.rms - rms) < 1e-3
    assert got["k1"] == pytest.approx(dist.ravel()[0], rel=1e-3)


@pytest.mark.slow
def test_corners_detected_in_zhangs_images_calibrate_the_camera(tmp_path):
    folder = shared_data("zhang")
    model_path = tmp_path / "zhang.mdl"
    text = (MODELS / "camera_calibration.mdl").read_text()  # the bundled example, with Zhang's target and size
    text = text.replace(
        "chessboard(rows = 6, cols = 9, square = 25 mm)",
        "squares(rows = 8, cols = 8, size = 0.5 inch, pitch = 0.888889 inch)",
    )
    model_path.write_text(text)
    images = sorted(str(p) for p in folder.glob("CalibIm*.png"))
    corners = tmp_path / "corners.json"
    run = [sys.executable, "-m", "mbcal"]
    detected = subprocess.run(
        [*run, "detect", *images, "--target", model_path, "-o", corners], capture_output=True, text=True, timeout=600
    )
    assert detected.returncode == 0, detected.stderr
    assert "1280 corners in 5 of 5 images" in detected.stdout
    # Every detected corner lies near one of Zhang's own measured corners.
    data = mbcal.read_measurements(corners, mbcal.load_model(model_path))
    for view in range(1, 6):
        theirs = np.loadtxt(folder / f"data{view}.txt").reshape(-1, 2)
        ours = np.array([m.value for m in data if m.config == f"CalibIm{view}"])
        nearest = np.linalg.norm(ours[:, None] - theirs[None], axis=2).min(axis=1)
        assert np.median(nearest) < 0.4 and nearest.max() < 1.0  # measured: 0.21-0.30 and 0.49-0.71 px
    report = tmp_path / "camera.json"
    calibrated = subprocess.run(
        [
            *run,
            "calibrate-camera",
            model_path,
            corners,
            "--estimate",
            "cam.fx",
            "cam.fy",
            "cam.cx",
            "cam.cy",
            "cam.k1",
            "cam.k2",
            "board.*",
            "--json",
            report,
            "--overlay",
            tmp_path / "reprojection",
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert calibrated.returncode == 0, calibrated.stderr
    assert "per view:" in calibrated.stdout and "RMS reprojection error" in calibrated.stdout
    result = json.loads(report.read_text())
    cam = result["cameras"]["cam"]
    for key in ("fx", "fy", "cx", "cy"):  # his camera model (k1, k2): measured within 0.15 %
        assert cam[key]["value"] == pytest.approx(ZHANG[key], rel=0.005), key
        assert cam[key]["std"] is not None and cam[key]["std"] > 0
    assert result["rms_reprojection"] < 0.5 and len(result["views"]) == 5
    assert len(list((tmp_path / "reprojection").glob("*.png"))) == 5


def test_a_view_whose_corners_give_no_homography_is_left_out_of_zhangs_start_and_named():
    """One view's corners on one row of the board (collinear) crashed the closed form with a
    traceback (SVD did not converge, after divide-by-zero warnings); a view of 3 corners was left
    out in silence.  Both are left out of the start and named; the solve then names the rotation
    about the row as unobservable."""
    import warnings

    from mbcal.problem import Problem
    from mbcal.workflows.cameras import default_unknowns

    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    data, _ = simulate_views(model, 6, {"cam.fx": 810.0}, seed=1, sigma=0.3)
    three = ("board.r0c0", "board.r3c4", "board.r5c8")
    keep = np.array(
        [
            (m.config != "view03" or m.refs["point"].startswith("board.r0c"))
            and (m.config != "view05" or m.refs["point"] in three)
            for m in data
        ]
    )
    data = data.subset(keep)
    names = Problem(model, data, default_unknowns(model, data)).params.names
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning either
        values, notes = zhang_start(model, data, names)
    assert notes == [
        "view03 (camera cam): its 9 points lie on one line on the target (no homography); Zhang's start left it "
        "out: the pose of 'board' there starts at the model's nominal values",
        "view05 (camera cam): only 3 point(s) of the target (a homography needs 4); Zhang's start left it out: "
        "the pose of 'board' there starts at the model's nominal values",
    ]
    assert values["cam.fx"] == pytest.approx(810.0, rel=0.01) and "board.x@view02" in values
    assert not any(name.endswith(("@view03", "@view05")) for name in values)
    cc = calibrate_cameras(model, data)
    assert [c.names for c in cc.result.observability.unobservable] == [["board.roll@view03"]]
    assert not cc.ok and cc.notes == notes and cc.to_json()["notes"] == notes
    assert cc.summary().splitlines()[1:3] == [f"note: {note}" for note in notes]


def test_closed_form_recovers_an_exact_camera():
    K = np.array([[800.0, 0.7, 320.0], [0, 790.0, 240.0], [0, 0, 1]])
    rng = np.random.default_rng(0)
    plane = np.stack(np.meshgrid(np.arange(7) * 0.03, np.arange(5) * 0.03), -1).reshape(-1, 2)
    Hs = []
    for _ in range(4):
        a, b, c = rng.uniform(-0.4, 0.4, 3)
        from mbcal.geometry.transforms import rpy

        R = rpy(np, a, b, c)[:3, :3]
        t = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), rng.uniform(0.4, 0.7)])
        cam = plane @ R[:, :2].T + t
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        H = homography(plane, uv)
        Hs.append(H)
        R2, t2 = pose_from_homography(K, H)
        np.testing.assert_allclose(R2, R, atol=1e-8)
        np.testing.assert_allclose(t2, t, atol=1e-9)
    np.testing.assert_allclose(intrinsics_from_homographies(Hs, skew=True), K, rtol=1e-7, atol=1e-6)


@pytest.mark.slow
def test_a_camera_with_full_distortion_is_recovered_from_synthetic_chessboard_images(tmp_path):
    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    truth = {
        "cam.fx": 812.0,
        "cam.fy": 806.5,
        "cam.cx": 327.0,
        "cam.cy": 236.0,
        "cam.k1": -0.21,
        "cam.k2": 0.08,
        "cam.p1": 0.001,
        "cam.p2": -0.0007,
        "cam.k3": 0.0,
    }
    views = plan_views(model, 10, seed=3)
    paths = synthesize_images(model, views, tmp_path, truth=truth)
    data, detections = detect_images(model, list(paths.values()))
    assert all(d.found for d in detections)
    cc = calibrate_cameras(model, data)
    assert cc.ok and cc.rms < 0.2
    for name, value in truth.items():
        est, std = cc.result.values[name], cc.result.std[name]
        assert abs(est - value) <= 3 * std + 1e-12, (name, est, value, std)


@pytest.mark.slow
def test_a_stereo_rig_is_recovered_from_synthetic_images_of_both_cameras(tmp_path):
    model = mbcal.load_model(MODELS / "stereo_calibration.mdl")
    truth = {
        "lens_left.fx": 790.0,
        "lens_left.fy": 788.0,
        "lens_left.cx": 322.0,
        "lens_left.cy": 241.0,
        "lens_left.k1": -0.12,
        "lens_right.fx": 805.0,
        "lens_right.fy": 803.0,
        "lens_right.cx": 317.0,
        "lens_right.cy": 236.0,
        "lens_right.k1": -0.1,
        "rig.x": 0.115,
        "rig.y": 0.003,
        "rig.z": -0.002,
        "rig.roll": np.radians(0.5),
        "rig.pitch": np.radians(-1.2),
        "rig.yaw": np.radians(0.8),
    }
    views = plan_views(model, 8, seed=5, distance=(0.5, 0.7), tilt_deg=25)
    left = synthesize_images(model, views, tmp_path / "left", truth=truth, camera="left")
    right = synthesize_images(model, views, tmp_path / "right", truth=truth, camera="right", seed=1)
    data_left, _ = detect_images(model, list(left.values()), camera="left")
    data_right, _ = detect_images(model, list(right.values()), camera="right")
    from mbcal.measurements.io import merge_measurements

    data = merge_measurements([data_left, data_right])
    cc = calibrate_cameras(model, data)
    assert cc.ok and len(cc.cameras) == 2
    for name, value in truth.items():
        est, std = cc.result.values[name], cc.result.std[name]
        assert abs(est - value) <= 3 * std + 1e-12, (name, est, value, std)


def test_detect_without_opencv_says_how_to_install_it(tmp_path):
    (tmp_path / "cv2.py").write_text("raise ImportError('no OpenCV here')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "mbcal",
            "detect",
            "x.png",
            "--target",
            str(MODELS / "camera_calibration.mdl"),
            "-o",
            str(tmp_path / "c.json"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert result.returncode == 2
    assert "needs OpenCV" in result.stderr and "pip install 'mbcal[vision]'" in result.stderr


@pytest.mark.slow
def test_auto_restarts_add_random_starts_only_when_zhangs_start_gives_a_doubtful_fit():
    """calibrate_cameras(restarts=None): Zhang's start alone when its fit converges and is
    consistent with σ; 4 starts (Zhang's first) when not; an explicit number is obeyed."""
    from mbcal.workflows.cameras import AUTO_RESTARTS, simulate_views

    model = mbcal.load_model(MODELS / "camera_calibration.mdl")
    truth = {"cam.fx": 810.0, "cam.fy": 805.0, "cam.cx": 322.0, "cam.cy": 238.0, "cam.k1": -0.2, "cam.k2": 0.05}
    data, _ = simulate_views(model, 6, truth, seed=4, sigma=0.3)
    cc = calibrate_cameras(model, data)
    assert len(cc.result.solver.cost) == 1 and cc.result.verdict.consistent
    assert cc.result.run.note.startswith("auto: Zhang's start alone")
    assert "restarts chosen: auto" in cc.result.summary()
    assert cc.result.to_json()["restarts"]["chosen"] == cc.result.run.note

    # ten times the stated noise: inconsistent with σ, so random starts join Zhang's
    rng = np.random.default_rng(1)
    noisy = data.with_values([m.value + rng.normal(0.0, 3.0, 2) for m in data])
    doubtful = calibrate_cameras(model, noisy)
    assert len(doubtful.result.solver.cost) == AUTO_RESTARTS and not doubtful.result.verdict.consistent
    assert f"auto: {AUTO_RESTARTS} starts" in doubtful.result.run.note
    alone = calibrate_cameras(model, noisy, restarts=1)
    np.testing.assert_allclose(doubtful.result.solver.x0[0], alone.result.solver.x0[0])  # Zhang's start first
    assert doubtful.result.cost <= alone.result.cost * (1 + 1e-9)

    explicit = calibrate_cameras(model, data, restarts=2)
    assert len(explicit.result.solver.cost) == 2 and explicit.result.run.note == ""


def test_the_camera_table_tells_a_fixed_intrinsic_from_one_the_views_do_not_determine(tmp_path):
    """σ None is a fixed intrinsic, σ = ∞ an estimated one the views do not determine: both were
    shown as 'fixed' (and null in the JSON, with nothing to tell them apart); one held at its hard
    limit showed σ 0 without saying why."""
    import dataclasses

    text = (MODELS / "camera_calibration.mdl").read_text()
    assert "param cam.k1 = 0 in [-1, 1]\n" in text
    path = tmp_path / "k1_limited.mdl"  # k1 may not go below 0: the true -0.2 holds it at that limit
    path.write_text(text.replace("param cam.k1 = 0 in [-1, 1]\n", "param cam.k1 = 0 in [0, 1] bounded\n"))
    model = mbcal.load_model(path)
    data, _ = simulate_views(model, 6, {"cam.fx": 810.0, "cam.k1": -0.2}, seed=0, sigma=0.3)
    cc = calibrate_cameras(model, data)
    assert "cam.k1" in cc.result.observability.active_bounds
    cam = cc.intrinsics["cam"]
    assert cam["skew"] == (0.0, None)  # not a parameter of the model: fixed
    assert all(s is not None and np.isfinite(s) for k, (_, s) in cam.items() if k != "skew")
    shown = dataclasses.replace(cc, intrinsics={"cam": {**cam, "k3": (cam["k3"][0], float("inf"))}})
    table = shown.summary().split("per view:")[0]
    rows = {line.split()[0]: line for line in table.splitlines()[3:] if line.strip()}
    assert rows["skew"].endswith("fixed") and rows["k3"].endswith("∞ (unobservable)")
    assert rows["k1"].endswith("0 (at bound)") and rows["fx"].split()[-1] == f"{cam['fx'][1]:.3g}"
    cameras = json.loads(json.dumps(shown.to_json(), allow_nan=False))["cameras"]["cam"]
    assert cameras["skew"] == {"value": 0.0, "std": None, "estimated": False}
    assert cameras["k3"]["std"] is None and cameras["k3"]["estimated"] is True
    assert cameras["fx"]["std"] == pytest.approx(cam["fx"][1]) and cameras["fx"]["estimated"] is True


def test_an_intrinsic_given_by_an_expression_shows_the_sigma_propagated_from_its_unknowns(tmp_path):
    """fy = fx · aspect with fx and aspect estimated: its σ is the one fy has when it is itself the
    unknown (the same model, parameterised otherwise: linear propagation is exact there); it read
    'fixed' before.  An expression of known parameters only stays fixed."""
    text = (MODELS / "camera_calibration.mdl").read_text()
    assert "fy = cam.fy, cx = cam.cx" in text and "param cam.fy = 800 in [300, 2000]\n" in text
    derived = text.replace("param cam.fy = 800 in [300, 2000]\n", "param cam.aspect = 1 in [0.9, 1.1]\n")
    derived = derived.replace("fy = cam.fy, cx = cam.cx", "fy = cam.fx * cam.aspect, cx = cam.cx + cam.shift")
    derived = derived.replace("param cam.cx =", "param cam.shift = 0\nparam cam.cx =")  # known: cx's σ is cam.cx's
    path = tmp_path / "aspect.mdl"
    path.write_text(derived)
    plain = mbcal.load_model(MODELS / "camera_calibration.mdl")
    model = mbcal.load_model(path)
    data, _ = simulate_views(plain, 6, {"cam.fx": 810.0, "cam.fy": 805.0, "cam.k1": -0.1}, seed=2, sigma=0.3)
    direct = calibrate_cameras(plain, data)
    via = calibrate_cameras(model, data)
    fy, fy_via = direct.intrinsics["cam"]["fy"], via.intrinsics["cam"]["fy"]
    assert fy_via[0] == pytest.approx(fy[0], rel=1e-8)
    assert fy_via[1] is not None and fy_via[1] == pytest.approx(fy[1], rel=1e-4)
    assert via.intrinsics["cam"]["cx"][1] == pytest.approx(via.result.std["cam.cx"], rel=1e-12)
    table = via.summary().split("per view:")[0]
    rows = {line.split()[0]: line for line in table.splitlines()[3:] if line.strip()}
    assert rows["fy"].split()[-1] == f"{fy_via[1]:.3g}"
    cameras = json.loads(json.dumps(via.to_json(), allow_nan=False))["cameras"]["cam"]
    assert cameras["fy"]["estimated"] is True and cameras["fy"]["std"] == pytest.approx(fy_via[1])

    # aspect known: fy = fx · 0.99 still reads an unknown; k3 = 2 · shift reads known parameters only: fixed
    known = derived.replace("param cam.aspect = 1 in [0.9, 1.1]\n", "param cam.aspect = 0.99\n")
    assert "k3 = cam.k3)" in known
    path.write_text(known.replace("k3 = cam.k3)", "k3 = 2 * cam.shift)"))
    fixed = calibrate_cameras(mbcal.load_model(path), data)
    assert fixed.intrinsics["cam"]["fy"][1] == pytest.approx(0.99 * fixed.result.std["cam.fx"], rel=1e-10)
    assert fixed.intrinsics["cam"]["k3"] == (0.0, None)
    rows = {line.split()[0]: line for line in fixed.summary().split("per view:")[0].splitlines()[3:] if line.strip()}
    assert rows["k3"].endswith("fixed") and not rows["fy"].endswith("fixed")


def test_zhangs_corners_doubled_are_refused_and_an_estimate_far_outside_its_range_is_noted(monkeypatch):
    """Zhang's corners with u, v doubled (most outside his 640×480 image) were calibrated with cx
    far outside its search range, 'consistent and well determined', exit 0."""
    import mbcal.measurements.sets as sets

    model = zhang_model(POINTS_FILE, skew=False)
    records = [
        {**vars_, "u": 2 * vars_["u"], "v": 2 * vars_["v"]}
        for vars_ in ({"kind": m.kind, "config": m.config, **m.refs, "u": m.value[0], "v": m.value[1]} for m in
                      zhang_corners(model))
    ]  # fmt: skip
    with pytest.raises(mbcal.MbcalError, match=r"of the 1280 image points of camera 'cam' lie outside its 640×480"):
        mbcal.measurements_from_records(records, model)
    # let through (as data built in Python would be): the report names the far-out estimates
    monkeypatch.setattr(sets, "IMAGE_MARGIN", float("inf"))
    cc = calibrate_cameras(model, mbcal.measurements_from_records(records, model))
    note = next(line for line in cc.summary().splitlines() if line.startswith("note: far outside the search range"))
    assert "cam.cx = " in note and "(search range [250, 390])" in note
    far = {entry["name"]: entry for entry in cc.result.to_json()["outside_search_range"]}  # and in the JSON
    assert far["cam.cx"]["lower"] == 250 and far["cam.cx"]["upper"] == 390 and far["cam.cx"]["value"] > 460
    plain = calibrate_cameras(model, zhang_corners(model))
    assert "far outside the search range" not in plain.summary()
    assert plain.result.to_json()["outside_search_range"] == []
