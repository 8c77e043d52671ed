"""`mbcal solve` with scan files beside clicked image points (issue 13: "solve accepting scan
files directly"), with real files on disk: a measurement CSV and a 16-bit depth PNG."""

from __future__ import annotations

import json

import numpy as np
import pytest

import mbcal
from mbcal.cli import main
from mbcal.range.fit import scan_measurements, scan_world_points
from mbcal.range.readers import write_depth_png, write_xyz
from mbcal.range.scans import Scan, load_scan

from conftest import MEASUREMENTS, MODELS

ROOM = str(MODELS / "room_depth.mdl")
TRUTH = {"room.x": 0.012, "room.y": -0.01, "room.z": 0.006, "room.yaw": np.radians(1.2)}


@pytest.mark.slow
def test_scan_measurements_name_the_object_and_crop():
    model = mbcal.load_model(ROOM)
    scene = mbcal.modeler(model, {})
    on_box = np.asarray(scene.shape_poses)[model.shape_index("room.box.housing"), :3, 3] + [0, -0.05, 0]
    far = np.array([5.0, 5.0, 5.0])  # nowhere near the model: cropped
    ms = scan_measurements(model, [Scan(np.array([on_box, far]), sigma=2e-3)], voxel=0)
    assert len(ms) == 1
    m = ms.measurements[0]
    assert m.kind == "point_to_surface" and m.id == "scan1.0"
    with pytest.raises(mbcal.MbcalError, match="no scan point lies within"):
        scan_measurements(model, [Scan(far[None], sigma=2e-3)], voxel=0)


def test_solve_without_inputs_is_exit_2(capsys):
    assert main(["solve", ROOM, "--estimate", "room.*"]) == 2
    assert "needs measurement files" in capsys.readouterr().err


def test_solve_with_a_malformed_scan_is_exit_2(tmp_path, capsys):
    bad = tmp_path / "scan.xyz"
    bad.write_text("0 0 1\n0 zero 1\n")
    assert main(["solve", ROOM, str(bad), "--estimate", "room.*"]) == 2
    err = capsys.readouterr().err
    assert "scan.xyz:2" in err and "Traceback" not in err


@pytest.mark.slow
def test_solve_clicks_and_a_depth_png_together(tmp_path, capsys):
    from mbcal.range.simulate import add_depth_noise, render_depth

    model = mbcal.load_model(ROOM)
    plan = mbcal.read_measurements(MEASUREMENTS / "room_plan.csv", model)
    clicks = mbcal.simulate(model, plan.subset([i < 12 for i in range(len(plan))]), TRUTH, seed=1)
    mbcal.write_measurements(clicks, tmp_path / "clicks.csv")
    write_depth_png(tmp_path / "depth.png", add_depth_noise(render_depth(model, TRUTH), 1e-3, 1e-3, seed=2))
    # A point cloud in CSV is a scan only through --scan (a positional .csv is a measurement file).
    cloud = load_scan(tmp_path / "depth.png", model)
    write_xyz(tmp_path / "cloud.csv", scan_world_points(model, cloud, TRUTH)[::40])
    report = tmp_path / "report.json"
    args = [
        "solve",
        ROOM,
        str(tmp_path / "clicks.csv"),
        str(tmp_path / "depth.png"),
        "--scan",
        str(tmp_path / "cloud.csv"),
    ]
    args += ["--estimate", "room.*", "--restarts", "2", "--scan-points", "300", "--json", str(report)]
    code = main(args)
    out = capsys.readouterr().out
    assert code == 0, out
    result = json.loads(report.read_text())
    for name, v in TRUTH.items():
        est, sd = result["parameters"][name]["value"], result["parameters"][name]["std"]
        assert abs(est - v) < 3 * sd + 1e-5, (name, est, v, sd)
    ids = {r["id"] for r in result["residuals"]}
    assert any(i.startswith("scan1.") for i in ids) and any(i.startswith("scan2.") for i in ids)
    assert {r["kind"] for r in result["residuals"]} == {"image_point", "point_to_surface"}


@pytest.mark.slow
def test_fit_writes_its_json_by_the_schema(tmp_path, capsys):
    """`mbcal fit --json`: the fit for machines, SI units named, valid against its schema; with
    '-' the JSON is stdout and the human report goes to stderr."""
    from importlib import resources

    import jsonschema

    from mbcal.range.simulate import add_depth_noise, render_depth

    model = mbcal.load_model(ROOM)
    write_depth_png(tmp_path / "depth.png", add_depth_noise(render_depth(model, TRUTH), 1e-3, 1e-3, seed=2))
    schema = json.loads((resources.files("mbcal") / "schemas" / "scan_fit.schema.json").read_text())
    out = tmp_path / "fit.json"
    code = main(["fit", ROOM, str(tmp_path / "depth.png"), "--estimate", "room.*", "--json", str(out), "--out",
                 str(tmp_path / "fitted")])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    doc = json.loads(out.read_text())
    jsonschema.validate(doc, schema)
    assert doc["format"] == "mbcal-scan-fit-1" and doc["units"]["room.yaw"] == "rad" and doc["units"]["room.x"] == "m"
    for name, truth in TRUTH.items():
        assert abs(doc["values"][name] - truth) < 4 * doc["std"][name], name
    # the report written beside the calibrated model is the same document
    beside = json.loads((tmp_path / "fitted" / "room_depth.fit.json").read_text())
    jsonschema.validate(beside, schema)
    assert beside["values"] == doc["values"]
    capsys.readouterr()
    assert main(["fit", ROOM, str(tmp_path / "depth.png"), "--estimate", "room.*", "--json", "-"]) == 0
    captured = capsys.readouterr()
    jsonschema.validate(json.loads(captured.out), schema)
    assert "room.x" in captured.err
    # σ stated 10× too small: not trustworthy, and the model written says so (it read as a clean one)
    doubted = tmp_path / "doubted"
    assert main(["fit", ROOM, str(tmp_path / "depth.png"), "--estimate", "room.*", "--sigma", "0.0001", "-q",
                 "--out", str(doubted)]) == 1  # fmt: skip
    header = (doubted / "room_depth.calibrated.mdl").read_text(encoding="utf-8").split("param", 1)[0]
    assert "# NOT A TRUSTWORTHY FIT: " in header and "the inliers scatter more than σ (reduced χ²" in header


def test_a_fit_that_fails_leaves_no_output_folder(tmp_path, capsys):
    """`mbcal fit --out DIR` made DIR before the fit, and left it empty when the fit failed."""
    far = tmp_path / "far.npy"
    np.save(far, 100.0 + np.random.default_rng(0).normal(size=(50, 3)))  # nowhere near the model
    out = tmp_path / "out"
    assert main(["fit", ROOM, str(far), "--estimate", "room.*", "--out", str(out)]) == 2
    assert "scan points lie within" in capsys.readouterr().err
    assert not out.exists()
