"""Every command end to end through the real command line (subprocesses), exit codes, JSON schema."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from importlib import resources

import jsonschema
import numpy as np
import pytest
from PIL import Image

from conftest import MEASUREMENTS, MODELS

ROOM = str(MODELS / "teleexistence.mdl")
ROOM_PLAN = str(MEASUREMENTS / "room_plan.csv")


def run(*args, cwd=None, timeout=600):
    return subprocess.run(
        [sys.executable, "-m", "mbcal", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=timeout
    )


def schema():
    return json.loads((resources.files("mbcal") / "schemas" / "report.schema.json").read_text())


SIMULATE = ["--set", "room.y=5cm", "--set", "room.yaw=1.2deg", "--set", "room.z=-1cm", "--noise", "1", "--seed", "3"]


@pytest.fixture(scope="module")
def room_csv(tmp_path_factory):
    out = tmp_path_factory.mktemp("room") / "room.csv"
    result = run("simulate", ROOM, ROOM_PLAN, *SIMULATE, "-o", out)
    assert result.returncode == 0, result.stderr
    assert "48 measurements" in result.stdout
    return out


def test_simulate_is_reproducible_for_a_seed(room_csv, tmp_path):
    again = tmp_path / "again.csv"
    result = run("simulate", ROOM, ROOM_PLAN, *SIMULATE, "-o", again)
    assert result.returncode == 0
    assert again.read_bytes() == room_csv.read_bytes()


@pytest.mark.slow
def test_solve_reports_writes_json_model_overlays_and_plot(room_csv, tmp_path):
    report = tmp_path / "report.json"
    model_out = tmp_path / "calibrated.mdl"
    overlays = tmp_path / "overlays"
    plot = tmp_path / "residuals.png"
    result = run(
        "solve",
        ROOM,
        room_csv,
        "--estimate",
        "room.*",
        "--restarts",
        "8",
        "--json",
        report,
        "--write-model",
        model_out,
        "--overlay",
        overlays,
        "--plot",
        plot,
    )
    assert result.returncode == 0, result.stderr
    text = result.stdout
    for expected in (
        "converged",
        "room.yaw",
        "observable: rank 6 of 6",
        "residuals, worst first",
        "restarts: 8",
        "line of sight",
    ):
        assert expected in text
    data = json.loads(report.read_text())
    jsonschema.validate(data, schema())
    assert data["status"] == "converged" and data["ok"] and data["observable"] and data["rank"] == 6
    assert abs(data["parameters"]["room.y"]["value"] - 0.05) < 3 * data["parameters"]["room.y"]["std"]
    assert len(data["residuals"]) == 48 and data["restarts"]["count"] == 8
    assert "room.yaw" in model_out.read_text()
    pngs = sorted(p.name for p in overlays.glob("*.png"))
    assert pngs == ["eyes_left_after.png", "eyes_left_before.png", "eyes_right_after.png", "eyes_right_before.png"]
    with Image.open(overlays / "eyes_left_after.png") as img:
        assert img.size == (669, 453)
    with Image.open(plot) as img:
        assert img.format == "PNG" and img.size[0] > 500


@pytest.mark.slow
def test_solve_with_json_to_stdout_and_quiet_prints_only_json(room_csv):
    # The parameters not estimated get their true values: fixed at 0 they would make the fit
    # inconsistent with the measurements' σ (and the exit status 1).
    known = ["--set", "room.yaw=1.2deg", "--set", "room.z=-1cm"]
    result = run(
        "solve", ROOM, room_csv, "--estimate", "room.x", "room.y", *known, "--restarts", "2", "--json", "-", "--quiet"
    )
    assert result.returncode == 0, result.stderr
    data = json.loads(result.stdout)
    jsonschema.validate(data, schema())
    assert set(data["parameters"]) == {"room.x", "room.y"}


@pytest.mark.slow
def test_solve_exits_1_when_something_is_not_observable(room_csv, tmp_path):
    report = tmp_path / "r.json"
    result = run("solve", ROOM, room_csv, "--estimate", "room.x", "robot.x", "--restarts", "2", "--json", report)
    assert result.returncode == 1
    assert "NOT observable" in result.stdout and "cannot be determined" in result.stdout
    data = json.loads(report.read_text())
    jsonschema.validate(data, schema())
    assert data["observable"] is False
    assert data["parameters"]["room.x"]["std"] is None
    assert {"room.x", "robot.x"} == set(data["unobservable"][0]["coefficients"])


def test_bad_measurement_file_exits_2_with_location_and_writes_nothing(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("kind,camera,point,u,v\nimage_point,eyes.left,lever.tip,1,2\nimage_point,eyes.left,lever.tpi,1,2\n")
    report = tmp_path / "report.json"
    result = run("solve", ROOM, bad, "--estimate", "room.*", "--json", report, cwd=tmp_path)
    assert result.returncode == 2
    assert any(
        line.startswith(f"{bad}:3:23: 'point': the model has no point named 'lever.tpi'")
        for line in result.stderr.splitlines()
    )
    assert "did you mean 'room.valve.lever.tip'" in result.stderr
    assert "Traceback" not in result.stderr
    assert not report.exists()


def test_unknown_estimate_name_exits_2_with_suggestion(room_csv):
    result = run("solve", ROOM, room_csv, "--estimate", "room.yow")
    assert result.returncode == 2
    assert "no parameter matches 'room.yow'" in result.stderr and "room.yaw" in result.stderr


def test_outputs_may_not_overwrite_inputs(room_csv):
    before = room_csv.read_bytes()
    result = run("solve", ROOM, room_csv, "--estimate", "room.*", "--json", room_csv)
    assert result.returncode == 2 and "refusing to overwrite the input file" in result.stderr
    assert room_csv.read_bytes() == before


@pytest.mark.slow
def test_observe_names_what_is_missing_and_what_would_help(tmp_path):
    plan = tmp_path / "few.csv"
    plan.write_text("kind,camera,point,sigma\nimage_point,eyes.left,lever.hub,1\nimage_point,eyes.left,lever.tip,1\n")
    report = tmp_path / "plan.json"
    result = run("observe", ROOM, plan, "--estimate", "room.*", "--json", report)
    assert result.returncode == 1
    assert "NOT observable: rank 4 of 6" in result.stdout
    assert "measurements that would help most" in result.stdout
    data = json.loads(report.read_text())
    jsonschema.validate(data, schema())
    assert data["kind"] == "plan" and len(data["unobservable"]) == 2
    full = run("observe", ROOM, ROOM_PLAN, "--estimate", "room.*")
    assert full.returncode == 0 and "observable: rank 6 of 6" in full.stdout


@pytest.mark.slow
def test_render_writes_a_png_of_the_cameras_size(tmp_path):
    out = tmp_path / "left.png"
    result = run("render", ROOM, "--camera", "eyes.left", "--set", "lever.angle=40deg", "--points", "-o", out)
    assert result.returncode == 0, result.stderr
    with Image.open(out) as img:
        assert img.size == (669, 453)
        pixels = np.asarray(img)
    assert pixels.std() > 10  # something was drawn


@pytest.mark.slow
def test_render_wireframe_over_a_photo(tmp_path):
    photo = tmp_path / "photo.png"
    Image.fromarray(np.full((453, 669, 3), 90, dtype=np.uint8)).save(photo)
    out = tmp_path / "overlay.png"
    result = run("render", ROOM, "--camera", "eyes.right", "--background", photo, "--wireframe", "-o", out)
    assert result.returncode == 0, result.stderr
    pixels = np.asarray(Image.open(out))
    red = (pixels[..., 0] > 150) & (pixels[..., 1] < 100)
    assert 500 < red.sum() < 0.2 * red.size  # edges drawn, the photo kept
    small = tmp_path / "small.png"
    Image.fromarray(np.zeros((10, 10, 3), dtype=np.uint8)).save(small)
    result = run("render", ROOM, "--background", small, "--wireframe", "-o", tmp_path / "x.png")
    assert result.returncode == 2 and "is 10×10 pixels but camera" in result.stderr


@pytest.mark.slow
def test_demo_runs_the_seeds_room_calibration_end_to_end(tmp_path):
    result = run("demo", "-o", tmp_path / "demo", "--restarts", "8")
    assert result.returncode == 0, result.stderr
    assert "observable: rank 6 of 6" in result.stdout

    def row(label: str) -> list[float]:
        # the lever's table: a label, then ⟂ and ∥ of this run (and the seed's, fixed text, ignored)
        line = next(line for line in result.stdout.splitlines() if line.strip().startswith(label))
        return [float(v) for v in re.findall(r"-?\d+\.\d+", line[len(label) + line.index(label) :])[:2]]

    before, after, sigma = row("before calibration"), row("after calibration"), row("predicted σ after")
    # The demo's perturbation of the room was chosen to give the seed's errors before calibration
    # (4.2 cm across and 16.5 cm along the line of sight, Tachi et al. section 4.1).
    np.testing.assert_allclose(before, [4.2, 16.5], rtol=0.1)
    # After: the calibrated pose's errors are within three of the predicted standard deviations
    # (simulated clicks, σ = 1 px) and far below the errors before.
    assert 0 <= after[0] <= 3 * sigma[0] and 0 <= after[1] <= 3 * sigma[1], (after, sigma)
    assert after[0] < before[0] / 4 and after[1] < before[1] / 4
    files = {p.name for p in (tmp_path / "demo").iterdir()}
    assert {
        "camera_left.png",
        "eyes_left_before.png",
        "eyes_left_after.png",
        "residuals.png",
        "report.json",
        "clicked_points.csv",
        "teleexistence_calibrated.mdl",
    } <= files
    jsonschema.validate(json.loads((tmp_path / "demo" / "report.json").read_text()), schema())


@pytest.mark.parametrize(
    "command",
    [
        "check",
        "scene",
        "solve",
        "simulate",
        "observe",
        "render",
        "demo",
        "detect",
        "calibrate-camera",
        "convert",
        "studio",
        "cache",
    ],
)
def test_every_command_has_help_with_an_example(command):
    result = run(command, "--help")
    assert result.returncode == 0
    assert "example:" in result.stdout and "mbcal " + command in result.stdout


def test_convert_writes_a_urdf_as_a_model_that_loads(tmp_path):
    from conftest import ROOT

    out = tmp_path / "arm7.mdl"
    result = run("convert", ROOT / "tests" / "data" / "arm7.urdf", "-o", out)
    assert result.returncode == 0, result.stderr
    import mbcal

    model = mbcal.load_model(out)
    assert "joint1.offset" in model.names("param")
