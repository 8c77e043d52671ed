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


def _scan_fit(chi2: float, dof: int):
    from mbcal.range.fit import ScanFit

    n = dof + 1
    return ScanFit(
        names=["room.x"], x=np.zeros(1), x_start=np.zeros(1), covariance=np.eye(1), information=np.eye(1),
        chi2=chi2, dof=dof, points=np.zeros((n, 3)), residuals=np.zeros(n), sigma=np.full(n, 2e-3),
        outlier=np.zeros(n, bool), cropped=0, far=np.zeros((0, 3)), total_points=n, misfits=[], coarse=None,
        elapsed=0.0, converged=True, outlier_sigma=3.0,
    )  # fmt: skip


def test_a_scatter_far_below_sigma_is_not_trustworthy():
    """σ stated too large hides a misfit (2 read as 2 m where 2 mm was meant: reduced χ² 2e-05 was
    'verdict: ok'): reduced χ² < 0.1, improbable for its dof, is a doubt; a small χ² that chance
    gives a few points, and a scatter a quiet sensor gives under its specified σ, are not."""
    tiny = _scan_fit(2.19e-05 * 24225, 24225)
    assert not tiny.ok and tiny.sigma_too_large
    assert any("σ stated too large" in d for d in tiny.doubts)
    assert "σ stated too large" in tiny.text().splitlines()[-1]
    assert "σ stated too large" in " ".join(tiny.to_json()["doubts"]) and tiny.to_json()["ok"] is False
    assert _scan_fit(0.3 * 24225, 24225).ok  # a sensor quieter than its σ: still ok
    assert _scan_fit(0.05, 1).ok  # one degree of freedom: χ² 0.05 happens by chance
    assert _scan_fit(1.0 * 100, 100).to_json()["doubts"] == []


def test_the_outlier_share_the_verdict_judges_is_that_of_the_points_near_the_model():
    """84 % of a scan's points beyond the crop distance (what it sees besides the model) printed
    '84.0 %' outliers beside 'verdict: ok', and a doubt said '50 % of the points are outliers' where
    the report said 100 %: the report and the doubt now say which share is judged."""
    import dataclasses

    fit = dataclasses.replace(_scan_fit(1.0 * 100, 100), cropped=500, far=np.ones((500, 3)), total_points=601)
    assert fit.ok and fit.outlier_fraction == pytest.approx(500 / 601) and fit.near_outlier_fraction == 0.0
    line = next(ln for ln in fit.text().splitlines() if ln.startswith("inliers:"))
    assert "500 (83.2 %): 500 beyond the crop distance" in line and "(0.0 % of the points within it" in line
    assert fit.to_json()["outliers"]["near_fraction"] == 0.0
    outlier = np.zeros(101, bool)
    outlier[:51] = True
    bad = dataclasses.replace(fit, outlier=outlier)
    assert not bad.ok
    said = "50 % of the points near the model (within the crop distance) are outliers"
    assert any(d.startswith(said) for d in bad.doubts)


def test_a_scan_nearly_all_beyond_the_crop_distance_gets_a_hint():
    """A cloud in millimetres read as metres: 12 of 24,261 points lay near the model's infinite
    planes, the fit was unobservable and nothing suggested units or frame."""
    import dataclasses
    from importlib import resources

    import jsonschema

    schema = json.loads((resources.files("mbcal") / "schemas" / "scan_fit.schema.json").read_text())
    base = _scan_fit(1.0 * 100, 100)  # 101 points near the model
    lost = dataclasses.replace(base, cropped=24249, far=np.ones((24249, 3)), total_points=24350)
    assert "note: 99.59 % of the points lay farther than the crop distance" in lost.text()
    assert "in metres" in lost.to_json()["hint"]
    jsonschema.validate(lost.to_json(), schema)
    fine = dataclasses.replace(base, cropped=800, far=np.ones((800, 3)), total_points=901)  # 89 %: a room around
    assert "crop distance from every" not in fine.text() and fine.to_json()["hint"] is None
    jsonschema.validate(fine.to_json(), schema)


def test_every_point_of_the_scans_is_accounted_for(tmp_path):
    """Six depth images gave 'scan fit: 60000 points used of 145552 (0 cropped …)': the 85,552
    above the cap went unsaid, and the outlier share mixed the subset with all the cropped points."""
    import dataclasses

    from mbcal.range.fit import FitOptions, fit_scans
    from mbcal.range.scans import Scan
    from mbcal.range.simulate import add_depth_noise, render_depth

    model = mbcal.load_model(ROOM)
    write_depth_png(tmp_path / "depth.png", add_depth_noise(render_depth(model, TRUTH), 1e-3, 1e-3, seed=2))
    world = scan_world_points(model, load_scan(tmp_path / "depth.png", model))
    far = 5.0 + np.arange(40.0)[:, None] * np.ones(3)  # 40 points nowhere near the model, 1.7 m apart
    cloud = Scan(np.vstack([world, far]))
    fit = fit_scans(model, [cloud], ["room.*"], FitOptions(max_points=3000, voxel=0.02))
    used, cropped, thinned, capped = len(fit.points), fit.cropped, fit.thinned, fit.capped
    assert 0 < cropped <= 40 and thinned > 0 and capped > 0 and used == 3000
    assert used + cropped + thinned + capped == fit.total_points == len(cloud)
    first = fit.text().splitlines()[0]
    said = f"({thinned} left out by the down-sampling, {cropped} cropped as far from the model, {capped} left out at"
    assert said in first
    report = fit.to_json()
    assert (report["thinned"], report["capped"], report["cropped"]) == (thinned, capped, cropped)
    share = fit.outlier_fraction  # the cropped points, and the near share standing for the capped points too
    assert share == pytest.approx((cropped + fit.near_outlier_fraction * (used + capped)) / (used + capped + cropped))
    same = dataclasses.replace(fit, capped=0)
    assert same.outlier_fraction == pytest.approx(same.n_outliers / (used + cropped))


def test_sigma_takes_a_unit_and_a_plain_number_is_metres(tmp_path, capsys):
    from mbcal.cli import build_parser

    parser = build_parser()
    for text, value in (("2mm", 0.002), ("2 mm", 0.002), ("0.002 m", 0.002), ("0.002", 0.002), ("0.5cm", 0.005)):
        assert parser.parse_args(["fit", ROOM, "a.png", "--estimate", "room.*", "--sigma", text]).sigma == value
        assert (
            parser.parse_args(["watch", ROOM, "--scans", "s", "--out", "o", "--estimate", "r", "--sigma", text]).sigma
            == value
        )
        assert (
            parser.parse_args(["solve", ROOM, "a.png", "--estimate", "room.*", "--scan-sigma", text]).scan_sigma
            == value
        )
    for text, why in (
        ("2deg", "not a unit of length"),
        ("two", "not a length"),
        ("0mm", "positive"),
        ("-1", "positive"),
    ):
        with pytest.raises(SystemExit) as stop:
            parser.parse_args(["fit", ROOM, "a.png", "--estimate", "room.*", f"--sigma={text}"])
        assert stop.value.code == 2
        err = capsys.readouterr().err
        assert "argument --sigma" in err and why in err, err
    for command in ("fit", "watch"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "plain number of METRES" in " ".join(capsys.readouterr().out.split())


@pytest.mark.slow
def test_sigma_in_metres_meant_as_mm_does_not_hide_a_depth_scale_error(tmp_path, capsys):
    """A depth image 10 % too deep fitted with --sigma 2 (metres; 2 mm was meant) was 'verdict: ok',
    exit 0: now exit 1, σ stated too large; the same with --sigma 2mm is not trustworthy either."""
    from mbcal.range.simulate import add_depth_noise, render_depth

    model = mbcal.load_model(ROOM)
    write_depth_png(tmp_path / "d.png", 1.1 * add_depth_noise(render_depth(model, TRUTH), 1e-3, 1e-3, seed=2))
    assert main(["fit", ROOM, str(tmp_path / "d.png"), "--estimate", "room.*", "--sigma", "2"]) == 1
    out = capsys.readouterr().out
    assert "σ 2e+03 mm" in out and "verdict: NOT trustworthy (the inliers scatter far less than σ" in out
    assert main(["fit", ROOM, str(tmp_path / "d.png"), "--estimate", "room.*", "--sigma", "2mm"]) == 1
    assert "σ 2 mm" in capsys.readouterr().out


@pytest.mark.parametrize("suffix", [".csv", ".npy", ".ply", ".pcd"])
def test_nonfinite_cloud_points_are_counted_and_reported(tmp_path, suffix):
    """NaN/inf points of a CSV, NPY or PLY cloud were dropped in silence (only PCD's were
    documented): the scan counts them (and notes it), the fit report's text and JSON state it."""
    from mbcal.range.readers import write_pcd, write_ply

    pts = np.random.default_rng(0).normal(size=(40, 3))
    pts[3] = np.nan
    pts[7, 1] = np.inf
    path = tmp_path / f"cloud{suffix}"
    if suffix == ".csv":
        write_xyz(path, pts, delimiter=",")
    elif suffix == ".npy":
        np.save(path, pts)
    elif suffix == ".ply":
        write_ply(path, pts)
    else:
        write_pcd(path, pts, binary=False)
    scan = load_scan(path, mbcal.load_model(ROOM))
    assert len(scan) == 38 and scan.nonfinite == 2 and scan.dropped == 2
    assert any("2 point(s) with a coordinate that is not a finite number" in n for n in scan.notes)
    fit = _scan_fit(100.0, 100)
    fit.nonfinite = 2
    assert "2 point(s) of the scans left out as read: a coordinate is not a finite number" in fit.text()
    assert fit.to_json()["nonfinite"] == 2 and _scan_fit(100.0, 100).to_json()["nonfinite"] == 0


def test_out_folder_holding_an_input_is_refused_only_when_an_output_would_replace_it(tmp_path, capsys):
    """`--out DIR` was refused when DIR merely held an input (a scan beside the results), though
    no output name collided: now only an output that would replace an input is refused."""
    import shutil

    from mbcal.range.manager import ModelManager, _check_out_dir, _fit_outputs
    from mbcal.range.readers import write_ply

    out = tmp_path / "out"
    out.mkdir()
    beside = out / "c.csv"
    _check_out_dir(out, [ROOM, beside], _fit_outputs("room_depth"), make=False)  # no collision: fine
    clash = out / "room_depth.outliers.ply"
    write_ply(clash, np.random.default_rng(0).normal(size=(30, 3)))
    assert main(["fit", ROOM, str(clash), "--estimate", "room.*", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "would replace the input" in err and "room_depth.outliers.ply" in err
    # the manager: its model kept in its own --out folder (no name of the journal, state or model)
    shutil.copytree(MODELS, out, dirs_exist_ok=True)  # the room's includes come along
    ModelManager(out / "room_depth.mdl", out, ["room.*"])
    assert (out / "room_depth.mdl").read_bytes() == (MODELS / "room_depth.mdl").read_bytes()


def test_process_noise_patterns_stand_for_the_estimated_unknowns_only(tmp_path, capsys):
    """`watch --process-noise 'lever.*=1deg'` checked the unit against lever.length too (not
    estimated, a length) and refused: a pattern stands for the estimated unknowns only."""
    scans = tmp_path / "scans"
    scans.mkdir()
    base = ["watch", ROOM, "--scans", str(scans), "--estimate", "room.*", "--estimate", "lever.angle", "--once"]
    assert main([*base, "--out", str(tmp_path / "a"), "--process-noise", "lever.*=1deg"]) == 0, capsys.readouterr()
    capsys.readouterr()
    assert main([*base, "--out", str(tmp_path / "b"), "--process-noise", "cam*=1mm"]) == 2
    err = capsys.readouterr().err
    assert "--process-noise cam*: matches no estimated unknown" in err and "lever.angle" in err
    assert not (tmp_path / "b").exists()  # a bad option leaves nothing behind
    assert main([*base, "--out", str(tmp_path / "c"), "--process-noise", "room.*=1deg"]) == 2  # room.x: a length
    assert "'deg' is not a unit of room.x" in capsys.readouterr().err


def test_watch_once_says_when_the_folder_holds_no_scan(tmp_path, capsys):
    """watch --once on an empty folder (or one of scans of a suffix mbcal does not read) printed
    nothing and exited 0, as a run that took every scan: it says there is no scan, and which files
    are scans.  The exit status stays 0, nothing new (docs/range.md)."""
    scans = tmp_path / "scans"
    scans.mkdir()
    base = ["watch", ROOM, "--scans", str(scans), "--estimate", "room.*", "--once"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    assert f"{scans}: no scan found (scans are .ply, .obj, .pcd" in out and ".tiff files)" in out
    assert "not looked at" not in out
    (scans / "room.las").write_bytes(b"LASF")
    (scans / ".hidden.ply").write_text("")
    assert main([*base, "--out", str(tmp_path / "b"), "--json"]) == 0
    captured = capsys.readouterr()
    assert captured.out == ""  # the JSON lines' stream holds updates only
    assert f"{scans}: no scan found" in captured.err and "; 1 other file not looked at" in captured.err
    assert main([*base, "--out", str(tmp_path / "c"), "--quiet"]) == 0
    assert capsys.readouterr() == ("", "")


def test_watch_skips_files_that_cannot_be_scans_with_a_note(tmp_path, capsys):
    """A README.txt, a log.csv of words and an 8-bit RGB photo.png beside the scans were rejected
    updates, and --once exited 1: they are skipped with a note (no update); a broken file of a
    scan's kind (a PNG cut short, a cloud with a bad line) stays a rejected update."""
    from PIL import Image

    scans = tmp_path / "scans"
    scans.mkdir()
    (scans / "README.txt").write_text("This folder holds the scans.\nCopy them here.\n")
    (scans / "log.csv").write_text("time,event\nmonday,started\n")
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(scans / "photo.png")
    base = ["watch", ROOM, "--scans", str(scans), "--estimate", "room.*", "--once"]
    assert main([*base, "--out", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out
    for name in ("README.txt", "log.csv", "photo.png"):
        assert f"{name}: skipped, not a scan" in out
    assert "update" not in out and not (tmp_path / "a" / "history.jsonl").exists()
    assert "8-bit image (mode RGB)" in out and "no scan found" not in out
    (scans / "broken.png").write_bytes(b"partial")
    assert main([*base, "--out", str(tmp_path / "b")]) == 1
    out = capsys.readouterr().out
    assert "update 1 (REJECTED, the scan cannot be read)" in out and "broken.png" in out and "update 2" not in out
    (tmp_path / "cloud.csv").write_text("x,y,z\n0,0,1\n")
    (tmp_path / "bad.txt").write_text("0 0 1\n0 zero 1\n")
    from mbcal.range.readers import not_a_scan

    assert not_a_scan(tmp_path / "cloud.csv") is None and not_a_scan(tmp_path / "bad.txt") is None
