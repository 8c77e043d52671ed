"""The command line refuses bad options before the work and never ends in a traceback: output
folders that cannot be written, a negative seed, values in a unit of the wrong dimension, a
photo of the wrong size, joint limits the wrong way round, a failing write; and a model written
from an untrustworthy fit says so in its header."""

from __future__ import annotations

import errno
import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from mbcal import cli
from mbcal.errors import MdlError, OutputError
from mbcal.language import load_model_text
from mbcal.outputs import check_output, check_output_folder

from conftest import MEASUREMENTS, MODELS

LEVER = str(MODELS / "lever.mdl")
LEVER_PLAN = str(MEASUREMENTS / "lever_plan.csv")


def run(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "mbcal", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600
    )


@pytest.fixture(scope="module")
def clicks(tmp_path_factory):
    """Simulated clicks of the lever at 35° (the model's length)."""
    out = tmp_path_factory.mktemp("lever") / "clicks.csv"
    result = run("simulate", LEVER, LEVER_PLAN, "--set", "lever.angle=35deg", "--seed", "1", "-o", out, "-q")
    assert result.returncode == 0, result.stderr
    return out


def test_an_output_folder_that_cannot_be_written_is_refused_before_the_work(tmp_path, monkeypatch):
    # os.access answers for the user running mbcal (root may write anywhere, so it is asked here).
    target = tmp_path / "out"
    target.mkdir()
    monkeypatch.setattr(cli.os, "access", lambda path, mode: False)
    with pytest.raises(OutputError, match="is not writable"):
        check_output(target / "report.json")
    with pytest.raises(OutputError, match="is not writable"):
        check_output_folder(target / "overlays", "--overlay")


def test_an_overlay_folder_under_a_file_is_refused_before_the_work(tmp_path, clicks):
    (tmp_path / "afile").write_text("mine\n")
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "-q", "--overlay", tmp_path / "afile" / "sub")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "cannot make the folder" in result.stderr and "is a file" in result.stderr
    assert (tmp_path / "afile").read_text() == "mine\n"


def test_a_write_the_system_refuses_is_an_error_not_a_traceback(tmp_path, monkeypatch, capsys):
    # The disk fills up as the finished file is flushed: the checks before the work cannot see it.
    def full(_fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("mbcal.outputs.os.fsync", full)
    code = cli.main(["simulate", LEVER, LEVER_PLAN, "-o", str(tmp_path / "plan.csv"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("error: No space left on device") and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []  # neither the file nor the temporary one is left


@pytest.mark.parametrize("command", ["solve", "simulate"])
def test_a_negative_seed_is_a_usage_error(tmp_path, clicks, command):
    args = [LEVER, clicks, "--estimate", "lever.angle"] if command == "solve" else [LEVER, LEVER_PLAN]
    result = run(command, *args, "--seed", "-1", "-o" if command == "simulate" else "-q", tmp_path / "x.csv")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "--seed: expected a whole number ≥ 0, got -1" in result.stderr
    assert not (tmp_path / "x.csv").exists()


def test_values_given_in_a_unit_of_another_dimension_are_refused(tmp_path, clicks):
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "--set", "lever.length=3deg")
    assert result.returncode == 2
    assert "--set lever.length: 'deg' is not a unit of lever.length, which is a length (m)" in result.stderr
    result = run("simulate", LEVER, LEVER_PLAN, "--set", "lever.angle=5cm", "-o", tmp_path / "s.csv")
    assert result.returncode == 2 and "which is an angle" in result.stderr
    assert not (tmp_path / "s.csv").exists()
    arm = MODELS / "arm7.mdl"
    result = run("kinematics", arm, "--point", "hand.tip", "--chain", "arm.q*", "--joints", "0,0,0,0,0,0,5cm")
    assert result.returncode == 2 and "--joints arm.q7: 'cm' is not a unit of arm.q7" in result.stderr
    result = run("kinematics", arm, "--point", "hand.tip", "--chain", "arm.q*", "--ik", "0.1,0.2,3deg")
    assert result.returncode == 2 and "the target's z" in result.stderr
    # The same values in units of their dimension, or plain SI numbers, are taken.
    result = run("simulate", LEVER, LEVER_PLAN, "--set", "lever.angle=0.6", "--set", "lever.length=25cm", "-o",
                 tmp_path / "s.csv", "-q")  # fmt: skip
    assert result.returncode == 0, result.stderr


def test_a_background_photo_of_the_wrong_size_is_refused_before_the_solve(tmp_path, clicks):
    Image.fromarray(np.zeros((480, 640, 3), dtype=np.uint8)).save(tmp_path / "photo.png")
    out = tmp_path / "overlays"
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "-q", "--overlay", out,
                 "--background", f"eye={tmp_path / 'photo.png'}")  # fmt: skip
    assert result.returncode == 2
    assert "the background is 640×480 pixels but camera 'eye' is 669×453" in result.stderr
    assert not out.exists()  # refused before anything was written
    Image.fromarray(np.full((453, 669, 3), 90, dtype=np.uint8)).save(tmp_path / "right.png")
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "-q", "--overlay", out,
                 "--background", f"eye={tmp_path / 'right.png'}")  # fmt: skip
    assert result.returncode == 0, result.stderr
    after = np.asarray(Image.open(out / "eye_after.png"))
    assert after.shape[:2] == (453, 669) and (after == 90).all(axis=-1).mean() > 0.5  # drawn over the photo


def test_render_takes_a_photo_alone_and_says_so_for_solves_camera_image_form(tmp_path):
    """render --help documented --background PHOTO while docs/cli.md said every --background is
    CAMERA=IMAGE (solve's form); given to render that form was 'image not found: eye=photo.png'."""
    Image.fromarray(np.zeros((453, 669, 3), dtype=np.uint8)).save(tmp_path / "photo.png")
    out = tmp_path / "r.png"
    result = run("render", LEVER, "--background", "eye=photo.png", "-o", out, cwd=tmp_path)
    assert result.returncode == 2
    assert "--background eye=photo.png: render takes the photo alone (CAMERA=IMAGE is solve's form)" in result.stderr
    assert "--camera eye --background photo.png" in result.stderr
    assert not out.exists()
    # each command's help and the documentation give the form it takes
    assert "--background PHOTO" in run("render", "--help").stdout
    assert "--background CAMERA=IMAGE" in run("solve", "--help").stdout
    text = " ".join((MODELS.parent / "docs" / "cli.md").read_text().split())
    assert "`render --background PHOTO` takes one photo" in text
    assert "`solve --background CAMERA=IMAGE` names the camera" in text


def test_joint_limits_the_wrong_way_round_are_an_error_at_the_lower_limit():
    text = "param q = 0 deg\nframe f {\n  joint revolute(z, q, lower = 30 deg, upper = -30 deg)\n}\n"
    with pytest.raises(MdlError) as info:
        load_model_text(text)
    assert "lower limit (30 deg) is above its upper limit (-30 deg)" in str(info.value)
    assert (info.value.span.line, info.value.span.column) == (3, 32)


def _mirror_camera(tmp_path):
    """The lever seen by a camera whose focal length is searched over [-1000, 1000] px, and two
    clicks: the fit ends at the mirror camera, f = -685 px (as good as +685)."""
    model = tmp_path / "levf.mdl"
    model.write_text(
        (MODELS / "lever.mdl")
        .read_text()
        .replace("camera eye(width = 669, height = 453, f = 600)", "param cam.f = 600 in [-1000, 1000]\n"
                 "camera eye(width = 669, height = 453, f = cam.f)")
    )  # fmt: skip
    clicks = tmp_path / "ok.csv"
    clicks.write_text(
        "id,kind,config,camera,point,u,v,sigma\n"
        "hub,image_point,default,eye,lever.hub,334.3,226.8,1.0\ntip,image_point,default,eye,lever.tip,237.2,61.5,1.0\n"
    )
    return model, clicks


def test_solve_refuses_to_write_a_model_its_estimate_makes_invalid(tmp_path):
    """With f searched over [-1000, 1000] the fit chose the mirror camera, f = -685; --write-model
    wrote 'param cam.f = -685.147...', a model 'mbcal check' refuses (fx must be positive)."""
    model, clicks = _mirror_camera(tmp_path)
    out = tmp_path / "levf_cal.mdl"
    result = run("solve", model, clicks, "--estimate", "cam.f", "lever.angle", "--restarts", "64",
                 "--accept-poor-fit", "-q", "--write-model", out)  # fmt: skip
    assert result.returncode == 2, result.stderr
    assert f"not writing {out}: camera 'eye': fx must be positive, got -685.1" in result.stderr
    assert "(the estimate cam.f = -685.1" in result.stderr and "Traceback" not in result.stderr
    assert not out.exists()
    # the report comes first: what the fit found, and that the estimate breaks the model
    result = run("solve", model, clicks, "--estimate", "cam.f", "lever.angle", "--restarts", "64",
                 "--accept-poor-fit", "--write-model", out)  # fmt: skip
    assert result.returncode == 2 and not out.exists() and f"not writing {out}" in result.stderr
    assert "the estimate breaks the model: " in result.stdout and "verdict: NOT trustworthy" in result.stdout


def test_an_estimate_that_breaks_the_model_is_not_trustworthy_even_accepted(tmp_path):
    """The same mirror fit without --write-model: it exited 0 with --accept-poor-fit, reporting
    f = -685 px as an estimate; now the verdict names the rule it breaks, where, and exit 1."""
    model, clicks = _mirror_camera(tmp_path)
    result = run("solve", model, clicks, "--estimate", "cam.f", "lever.angle", "--restarts", "64",
                 "--accept-poor-fit", "--json", "-")  # fmt: skip
    assert result.returncode == 1, result.stderr
    fit = json.loads(result.stdout)["fit"]
    assert fit["ok"] is False and fit["accepted"] is True
    assert fit["invalid_estimate"].startswith(f"{model}:") or fit["invalid_estimate"].startswith("levf.mdl:")
    assert "camera 'eye': fx must be positive, got -685.1" in fit["invalid_estimate"]
    assert "at the estimate" in fit["invalid_estimate"]
    assert "NOT trustworthy: the estimate breaks the model" in fit["verdict"]
    assert "even with --accept-poor-fit" in fit["verdict"]
    assert "the estimate breaks the model: " in result.stderr
    # the same search range with hard limits that keep f valid: the other solution, untouched
    model.write_text(model.read_text().replace("in [-1000, 1000]", "in [300, 1000] limits [1, 1e6]"))
    result = run("solve", model, clicks, "--estimate", "cam.f", "lever.angle", "--restarts", "64", "--json", "-")
    assert json.loads(result.stdout)["fit"]["invalid_estimate"] is None


def test_a_value_so_large_that_its_residual_overflows_is_located(tmp_path):
    """u = 1e308 px: every restart failed ("the residuals are not finite at any starting point")
    without a word of which measurement; now the message names it at its file:line:col."""
    clicks = tmp_path / "huge.csv"
    clicks.write_text(
        "id,kind,config,camera,point,u,v,sigma\n"
        "tip,image_point,default,eye,lever.tip,237.2,61.5,1.0\nhub,image_point,default,eye,lever.hub,1e308,1e308,1.0\n"
    )
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "--restarts", "4")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{clicks}:3:" in result.stderr or "huge.csv:3:" in result.stderr, result.stderr
    assert "every restart failed" in result.stderr and "the first 'hub'" in result.stderr


def test_a_model_written_from_an_untrustworthy_fit_says_so_in_its_header(tmp_path):
    # Clicks of a lever 10 cm longer than the model's: the fit cannot be consistent with 1 px.
    data = tmp_path / "long.csv"
    result = run("simulate", LEVER, LEVER_PLAN, "--set", "lever.angle=35deg", "--set", "lever.length=35cm",
                 "--seed", "1", "-o", data, "-q")  # fmt: skip
    assert result.returncode == 0, result.stderr
    bad, good = tmp_path / "bad.mdl", tmp_path / "good.mdl"
    result = run("solve", LEVER, data, "--estimate", "lever.angle", "-q", "--write-model", bad)
    assert result.returncode == 1
    header = bad.read_text().split("\n\n")[0]
    assert "# NOT A TRUSTWORTHY FIT" in header and "# verdict: NOT trustworthy" in header
    clicks = tmp_path / "clicks.csv"
    run("simulate", LEVER, LEVER_PLAN, "--set", "lever.angle=35deg", "--seed", "1", "-o", clicks, "-q")
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle", "-q", "--write-model", good)
    assert result.returncode == 0, result.stderr
    assert "TRUSTWORTHY" not in good.read_text()


def test_an_unknown_option_gets_the_commands_own_usage():
    result = run("solve", LEVER, "--bogus")
    assert result.returncode == 2
    assert (
        "usage: mbcal solve" in result.stderr and "mbcal solve: error: unrecognized arguments: --bogus" in result.stderr
    )


def test_an_unknown_camera_lists_the_models_cameras(tmp_path):
    result = run("render", LEVER, "--camera", "nope", "-o", tmp_path / "x.png")
    assert result.returncode == 2 and "no camera named 'nope' (the model's cameras: eye)" in result.stderr


def test_render_refuses_a_camera_larger_than_it_draws_where_it_is_declared(tmp_path):
    """A 16385 px wide camera passed check and ended render in an OpenGL traceback, exit status 1."""
    model = tmp_path / "wide.mdl"
    model.write_text("camera c(width = 16385, height = 100, f = 600)\nshape box(1 m, 1 m, 1 m) at (0, 0, 5 m)\n")
    for command in (("check", model), ("render", model, "-o", tmp_path / "x.png")):
        result = run(*command)
        assert result.returncode == 2, result.stderr
        assert "wide.mdl:1:18: the camera's width must be a whole number of pixels in 1..16384" in result.stderr
        assert "Traceback" not in result.stderr
    assert not (tmp_path / "x.png").exists()


def test_the_report_says_converged_once(clicks):
    result = run("solve", LEVER, clicks, "--estimate", "lever.angle")
    assert result.returncode == 0, result.stderr
    assert "converged: S changed" in result.stdout and "converged: converged" not in result.stdout


def test_a_zero_scan_sigma_is_refused(tmp_path):
    result = run("fit", MODELS / "room_depth.mdl", tmp_path / "scan.png", "--estimate", "room.*", "--sigma", "0")
    assert result.returncode == 2 and "argument --sigma: must be a positive length" in result.stderr
    result = run("solve", MODELS / "room_depth.mdl", tmp_path / "s.png", "--estimate", "room.*", "--scan-sigma", "0")
    assert result.returncode == 2 and "argument --scan-sigma: must be a positive length" in result.stderr


@pytest.fixture()
def room_copy(tmp_path):
    """The teleexistence model copied with the file it includes and the mesh it reads."""
    import shutil

    for part in ("teleexistence.mdl", "parts", "meshes"):
        source = MODELS / part
        (shutil.copytree if source.is_dir() else shutil.copy)(source, tmp_path / part)
    return tmp_path


@pytest.mark.parametrize(
    "argv, victim",
    [
        (
            ["observe", "teleexistence.mdl", "plan.csv", "--estimate", "room.*", "--json", "parts/stereo.mdl"],
            "parts/stereo.mdl",
        ),
        (["scene", "teleexistence.mdl", "-o", "meshes/gauge_bezel.obj"], "meshes/gauge_bezel.obj"),
        (["observe", "teleexistence.mdl", "plan.csv", "--json", "meshes/gauge_bezel.obj"], "meshes/gauge_bezel.obj"),
    ],
)
def test_an_output_never_replaces_a_file_the_model_includes_or_reads(room_copy, monkeypatch, capsys, argv, victim):
    """--json, --plot and -o were checked against the model file only: an included file or a mesh
    the model reads was overwritten (exit 0)."""
    import shutil

    shutil.copy(MEASUREMENTS / "room_plan.csv", room_copy / "plan.csv")
    monkeypatch.chdir(room_copy)
    before = (room_copy / victim).read_bytes()
    assert cli.main(argv) == 2
    assert "refusing to overwrite the input file" in capsys.readouterr().err
    assert (room_copy / victim).read_bytes() == before


def test_two_outputs_at_one_path_or_an_empty_name_are_refused_before_the_work(tmp_path, clicks, capsys):
    for extra in (["--json", "r.json", "--write-model", "r.json"], ["--json", ""]):
        out = [str(tmp_path / a) if a.endswith(".json") else a for a in extra]
        assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", *out]) == 2
        err = capsys.readouterr().err
        assert ("--json and --write-model both name" in err) if len(extra) == 4 else ("--json needs a file name" in err)
    assert list(tmp_path.iterdir()) == []


def test_dash_is_standard_output_for_json_only(tmp_path, clicks, capsys, monkeypatch):
    """`--write-model -` wrote a file named '-' after the solve."""
    monkeypatch.chdir(tmp_path)
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", "--write-model", "-"]) == 2
    assert "--write-model needs a file name: '-' (standard output) is taken by --json only" in capsys.readouterr().err
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", "--overlay", "-"]) == 2
    assert "--overlay needs a folder name: '-'" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", "--json", "-"]) == 0
    assert '"lever.angle"' in capsys.readouterr().out


def test_observe_applies_set_and_values_on_the_command_line_must_keep_the_model_valid(tmp_path, capsys):
    """observe ignored --set (a 1 mm lever read 0.294° instead of 79°); scene and render drew a box
    of negative size from --set; a value outside a parameter's hard limits was taken."""
    import json

    sigmas = []
    for extra in ([], ["--set", "lever.length=1mm"]):
        out = tmp_path / f"o{len(extra)}.json"
        cli.main(["observe", LEVER, LEVER_PLAN, "--estimate", "lever.angle", "-q", "--json", str(out), *extra])
        sigmas.append(json.loads(out.read_text())["parameters"]["lever.angle"]["std"])
    assert sigmas[1] > 100 * sigmas[0]  # σ grows as the lever shrinks: ~250× for 25 cm → 1 mm
    assert cli.main(["scene", LEVER, "--set", "lever.length=-1", "-o", str(tmp_path / "x.ply")]) == 2
    assert "must be positive, got -1 m with the values of --set" in capsys.readouterr().err
    limited = tmp_path / "limited.mdl"
    limited.write_text(
        open(LEVER).read().replace("param lever.length = 25 cm", "param lever.length = 25 cm limits [20 cm, 30 cm]")
    )
    assert cli.main(["scene", str(limited), "--set", "lever.length=50cm", "-o", str(tmp_path / "x.ply")]) == 2
    err = capsys.readouterr().err
    line = limited.read_text().splitlines().index("param lever.length = 25 cm limits [20 cm, 30 cm]") + 1
    assert (
        f"{limited}:{line}:1: --set lever.length: 0.5 m is outside the hard limits of lever.length [0.2, 0.3] m" in err
    )
    assert not (tmp_path / "x.ply").exists()


def test_a_shape_pose_that_is_not_finite_is_a_model_error():
    with pytest.raises(MdlError, match=r"2:\d+: the pose of shape 'o.shape0' is not finite at the nominal values"):
        load_model_text("object o {\n  shape box(1 m, 1 m, 1 m) at quat(0, 0, 0, 0)\n}\n")


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["solve", LEVER, LEVER_PLAN, "--outlier-threshold", "-1"],
            "--outlier-threshold: expected a number ≥ 0, got -1",
        ),
        (
            ["solve", LEVER, LEVER_PLAN, "--outlier-threshold", "nan"],
            "--outlier-threshold: expected a number ≥ 0, got nan",
        ),
        (["kinematics", LEVER, "lever.tip", "--tolerance", "-1"], "--tolerance: expected a number > 0, got -1"),
        (["kinematics", LEVER, "lever.tip", "--restarts", "0"], "--restarts: expected a whole number ≥ 1, got 0"),
        (
            ["fit", LEVER, "s.ply", "--estimate", "lever.angle", "--restarts", "0"],
            "--restarts: expected a whole number ≥ 1",
        ),
        (
            ["watch", LEVER, "--scans", "in", "--out", "out", "--estimate", "x", "--poll", "-1"],
            "--poll: expected a number > 0",
        ),
        (
            ["watch", LEVER, "--scans", "in", "--out", "out", "--estimate", "x", "--drift-k", "0"],
            "--drift-k: expected a number > 0",
        ),
        (["calibrate-camera", LEVER, "c.json", "--restarts", "0"], "--restarts: expected a whole number ≥ 1, got 0"),
    ],
)
def test_option_values_that_make_no_sense_are_usage_errors(tmp_path, monkeypatch, capsys, argv, message):
    """Accepted before: a negative outlier threshold listed every measurement, NaN none; a negative
    IK tolerance called a reached target out of reach; zero restarts ran (or failed after the work)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2 and message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_calibrate_camera_checks_its_images_before_the_solve(tmp_path, capsys, monkeypatch):
    """--image of a configuration with no corners was ignored, one of the wrong size drawn at that
    size, a missing one found only after the whole solve."""
    import mbcal
    from mbcal.measurements.io import write_measurements
    from mbcal.workflows.cameras import simulate_views

    model_path = MODELS / "camera_calibration.mdl"
    model = mbcal.load_model(model_path)
    data, _ = simulate_views(model, 3, {"cam.fx": 810.0}, seed=1, sigma=0.3)
    corners = tmp_path / "corners.csv"
    write_measurements(data, corners)
    view = data.measurements[0].config
    Image.new("RGB", (100, 100)).save(tmp_path / "small.png")
    Image.new("RGB", (640, 480)).save(tmp_path / "right.png")
    solved = []
    monkeypatch.setattr("mbcal.workflows.cameras.calibrate_cameras", lambda *a, **k: solved.append(1))
    cases = [
        (f"nope={tmp_path / 'right.png'}", "no corners were measured in a configuration 'nope'"),
        (f"{view}={tmp_path / 'small.png'}", "the background is 100×100 pixels but camera 'cam' is 640×480"),
        (f"{view}={tmp_path / 'missing.png'}", "image not found"),
    ]
    for image, message in cases:
        code = cli.main(
            ["calibrate-camera", str(model_path), str(corners), "--image", image, "--overlay", str(tmp_path / "ov")]
        )
        assert code == 2 and message in capsys.readouterr().err
    right = f"{view}={tmp_path / 'right.png'}"
    for extra, message in (
        (["--image", right], "--image is for the overlays: give --overlay DIR too"),
        (["--image", f"{view}=", "--overlay", str(tmp_path / "ov")], "no file name after '='"),
        (["--image", right, "--image", right, "--overlay", str(tmp_path / "ov")], f"--image {view} is given twice"),
    ):
        assert cli.main(["calibrate-camera", str(model_path), str(corners), *extra]) == 2
        assert message in capsys.readouterr().err
    assert solved == []  # refused before the solve
    (tmp_path / "ov").mkdir()
    photo = tmp_path / "ov" / f"{view}_cam_reprojection.png"  # the name its overlay would have
    Image.new("RGB", (640, 480)).save(photo)
    before = photo.read_bytes()
    argv = [
        "calibrate-camera",
        str(model_path),
        str(corners),
        "--image",
        f"{view}={photo}",
        "--overlay",
        str(photo.parent),
    ]
    assert cli.main(argv) == 2
    assert f"refusing to overwrite the input file {photo}" in capsys.readouterr().err
    assert photo.read_bytes() == before and solved == []


def test_calibrate_camera_checks_the_measurement_files_images_before_the_solve(tmp_path, capsys, monkeypatch):
    """--overlay with corners from 'mbcal detect -o corners.csv' (CSV keeps no image paths), or with
    a JSON file moved away from its images (paths relative to its folder), failed after the whole
    solve and threw the calibration away; the hint said to run 'mbcal detect', which made them."""
    import shutil

    import mbcal
    from mbcal.measurements.io import write_measurements
    from mbcal.workflows.cameras import simulate_views

    model_path = MODELS / "camera_calibration.mdl"
    data, _ = simulate_views(mbcal.load_model(model_path), 3, {"cam.fx": 810.0}, seed=1, sigma=0.3)
    views = list(dict.fromkeys(m.config for m in data))
    for view in views:
        Image.new("RGB", (640, 480)).save(tmp_path / f"{view}.png")
    data.images = {view: str(tmp_path / f"{view}.png") for view in views}
    write_measurements(data, tmp_path / "corners.csv")
    write_measurements(data, tmp_path / "corners.json")
    (tmp_path / "moved").mkdir()
    shutil.copy(tmp_path / "corners.json", tmp_path / "moved" / "corners.json")
    Image.new("RGB", (320, 240)).save(tmp_path / "small.png")
    small = dict(data.images, **{views[1]: str(tmp_path / "small.png")})
    data.images = small
    write_measurements(data, tmp_path / "small.json")
    solved = []

    class SolvedError(Exception):
        pass

    def solve(*args, **kwargs):
        solved.append(1)
        raise SolvedError

    monkeypatch.setattr("mbcal.workflows.cameras.calibrate_cameras", solve)
    overlay = ["--overlay", str(tmp_path / "ov")]
    cases = [
        (
            tmp_path / "corners.csv",
            [
                "--overlay needs the views' images, and no measurement file names them",
                f"a CSV file ({tmp_path / 'corners.csv'}) carries no image paths",
                "-o corners.json",
            ],
        ),
        (
            tmp_path / "moved" / "corners.json",
            [f"{tmp_path / 'moved' / 'corners.json'}: the image of {views[0]}: image not found"],
        ),
        (tmp_path / "small.json", [f"the image of {views[1]}:", "is 320×240 pixels but camera 'cam' is 640×480"]),
    ]
    for corners, messages in cases:
        assert cli.main(["calibrate-camera", str(model_path), str(corners), *overlay]) == 2
        err = capsys.readouterr().err
        assert all(message in err for message in messages), err
    assert solved == [] and not (tmp_path / "ov").exists()  # refused before the solve
    # --image gives what the CSV file lacks; without --overlay the images are not needed
    images = [arg for view in views for arg in ("--image", f"{view}={tmp_path / f'{view}.png'}")]
    with pytest.raises(SolvedError):
        cli.main(["calibrate-camera", str(model_path), str(tmp_path / "corners.csv"), *images, *overlay])
    with pytest.raises(SolvedError):
        cli.main(["calibrate-camera", str(model_path), str(tmp_path / "moved" / "corners.json")])
    assert len(solved) == 2


def test_an_input_file_given_twice_is_refused(clicks, capsys):
    """It was read twice: 'duplicate id (first at lever.csv:2:1)', pointing at the very same place."""
    assert cli.main(["solve", LEVER, str(clicks), str(clicks), "--estimate", "lever.angle", "-q"]) == 2
    assert f"{clicks} is given twice" in capsys.readouterr().err


def test_an_overlay_never_replaces_a_photo_it_was_drawn_over_and_its_folder_is_checked(
    tmp_path, clicks, capsys, monkeypatch
):
    """--background pointing into the --overlay folder at a name the overlay writes was replaced by
    the new picture (exit 0), then refused only after the solve; --overlay '' was ignored; an
    --overlay folder the system refuses was found after the solve; a folder and a file at one path
    were found after the overlays."""
    import mbcal.api

    base = ["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q"]
    folder = tmp_path / "ov"
    assert cli.main([*base, "--overlay", str(folder)]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["eye_after.png", "eye_before.png"]
    photo = folder / "eye_after.png"
    before = photo.read_bytes()
    solved = []
    with monkeypatch.context() as patch:
        patch.setattr(mbcal.api, "calibrate", lambda *a, **k: solved.append(1))
        assert cli.main([*base, "--overlay", str(folder), "--background", f"eye={photo}"]) == 2
    assert f"refusing to overwrite the input file {photo}" in capsys.readouterr().err
    assert photo.read_bytes() == before and solved == []
    assert cli.main([*base, "--overlay", ""]) == 2
    assert "--overlay needs a folder name" in capsys.readouterr().err
    same = str(tmp_path / "r.mdl")
    assert cli.main([*base, "--overlay", same, "--write-model", same]) == 2
    assert "--write-model and --overlay both name" in capsys.readouterr().err
    assert not (tmp_path / "r.mdl").exists()


@pytest.mark.parametrize(("option", "name"), [("--json", "eye_before.png"), ("--plot", "eye_after.png")])
def test_an_output_named_like_an_overlay_is_refused_before_the_solve(clicks, tmp_path, capsys, option, name):
    """--json ov/eye_before.png with --overlay ov: the overlay replaced the report (or the plot the
    overlay) and the command said nothing."""
    folder = tmp_path / "ov"
    folder.mkdir()
    target = folder / name
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", option, str(target),
                     "--overlay", str(folder)]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert f"{option} names {target}, a picture --overlay writes: one would replace the other" in err
    assert not target.exists()


def test_a_value_given_twice_and_images_without_overlays_are_refused(clicks, capsys):
    base = ["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q"]
    assert cli.main([*base, "--set", "lever.length=25cm", "--set", "lever.length=30cm"]) == 2  # the last won
    assert "--set lever.length is given twice" in capsys.readouterr().err


@pytest.mark.parametrize("loss", [[], ["--loss", "linear"]])
def test_a_loss_scale_without_a_robust_loss_is_refused(clicks, capsys, loss):
    """--loss-scale 3 without --loss (or with the linear one) was ignored in silence: a plain
    least-squares fit, exit status 0, that the user took for a robust one."""
    args = ["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", *loss, "--loss-scale", "3"]
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert "--loss-scale is the scale of a robust loss" in err
    assert "give --loss huber or --loss cauchy with it" in err


@pytest.mark.parametrize("set_", ["lever.angle=60deg", "lever.an*=60deg"])
def test_observe_refuses_at_and_set_for_the_same_parameter(capsys, set_):
    """observe --at lever.angle=5deg --set lever.angle=60deg analysed at 5° in silence."""
    args = ["observe", LEVER, LEVER_PLAN, "--estimate", "lever.angle", "-q", "--at", "lever.angle=5deg"]
    assert cli.main([*args, "--set", set_]) == 2
    err = capsys.readouterr().err
    assert f"--at lever.angle and --set {set_.split('=')[0]} both give a value of lever.angle: give one" in err
    assert cli.main([*args, "--set", "lever.length=30cm"]) != 2  # another parameter: no conflict


def test_a_plot_named_other_than_png_is_refused_before_the_solve(clicks, tmp_path, capsys):
    """--plot p.jpg wrote PNG data into a .jpg file (render refuses such a name)."""
    target = tmp_path / "p.jpg"
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "-q", "--plot", str(target)]) == 2
    assert f"--plot writes a PNG image: give a name ending in .png, got {target}" in capsys.readouterr().err
    assert not target.exists()


def test_check_checks_every_model_it_is_given(tmp_path, capsys):
    """'mbcal check bad1 good bad2' stopped at bad1: bad2 was never read."""
    (tmp_path / "bad1.mdl").write_text("param a = \n", encoding="utf-8")
    (tmp_path / "bad2.mdl").write_text("object x at (0, 0, 1 deg) {}\n", encoding="utf-8")
    assert cli.main(["check", str(tmp_path / "bad1.mdl"), LEVER, str(tmp_path / "bad2.mdl"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "bad1.mdl:1:11: unexpected end of file" in err
    assert "bad2.mdl:1:13: a position must be a length (m), got an angle (rad)" in err
    assert "2 of 3 models failed the check" in err
    assert cli.main(["check", LEVER, LEVER]) == 0 and "ok: 2 models checked" in capsys.readouterr().out


def test_solve_refuses_bad_unknowns_or_a_plan_before_it_says_it_is_solving(clicks, capsys):
    """'… compiling and solving 2 restarts' was printed, then 'no parameter matches ...': the
    unknowns and the measured values are checked before the solve's progress line."""
    bad = [
        ([str(clicks), "--estimate", "lever.nothing"], "no parameter matches 'lever.nothing'"),
        ([LEVER_PLAN, "--estimate", "lever.angle"], "is this a measurement plan?"),
    ]
    for argv, message in bad:
        assert cli.main(["solve", LEVER, *argv, "--restarts", "2"]) == 2
        err = capsys.readouterr().err
        assert message in err and "solving" not in err, err
    assert cli.main(["solve", LEVER, str(clicks), "--estimate", "lever.angle", "--restarts", "2"]) == 0
    err = capsys.readouterr().err
    assert "… solving: 1 unknowns," in err and "2 restarts" in err, err


def test_solve_shows_the_warning_of_a_row_pasted_twice(tmp_path, clicks, capsys):
    rows = [line.split(",", 1)[1] for line in clicks.read_text().splitlines()]  # without the ids
    twice = tmp_path / "twice.csv"
    twice.write_text("\n".join([*rows, rows[1]]) + "\n")
    assert cli.main(["solve", LEVER, str(twice), "--estimate", "lever.angle", "--restarts", "2", "-q"]) == 0
    assert f"warning: {twice}:{len(rows) + 1}: row repeats line 2 (" in capsys.readouterr().err
