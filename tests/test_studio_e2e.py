"""The studio end to end in Chromium: the seed's room calibration clicked by hand in the page
(photos rendered at known true values), and Zhang's real photograph of his target (his
published pose for view 1).  The walk-through's screenshots in docs/images/ are taken here
(with MBCAL_DOC_IMAGES=docs/images; otherwise into a temporary folder)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from test_studio import BLOCK_CLICKS, SMALL, _blocked_solve, _photo, _session_when, click_point, open_page

from mbcal.studio.engine import Engine
from mbcal.studio.server import StudioServer

from conftest import ROOT, run_python, shared_data

# The screenshots go to a temporary folder; `MBCAL_DOC_IMAGES=docs/images` writes them over the
# walk-through's pictures in docs/studio.md instead (a test run never changes the checkout unasked).
IMAGES_FOLDER = os.environ.get("MBCAL_DOC_IMAGES")


@pytest.fixture(scope="module")
def images(tmp_path_factory) -> Path:
    folder = Path(IMAGES_FOLDER) if IMAGES_FOLDER else tmp_path_factory.mktemp("screenshots")
    folder = folder if folder.is_absolute() else ROOT / folder
    folder.mkdir(parents=True, exist_ok=True)
    return folder


pytestmark = pytest.mark.slow


def _start_cli(args: list[str], cwd: Path) -> tuple[subprocess.Popen, str]:
    """``mbcal studio ... --no-browser`` in a subprocess; returns it and the URL it printed."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbcal", "studio", *args, "--no-browser"],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.search(r"(http://127\.0\.0\.1:\d+/\?token=\S+)", line)
        if m:
            # Keep reading what it prints, so that a full pipe never blocks the server.
            threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
            return proc, m.group(1)
    proc.wait(timeout=10)
    raise AssertionError(f"mbcal studio printed no URL (exit {proc.returncode})")


def test_the_room_clicked_in_the_page_is_found_within_three_sigma(browser, images, tmp_path):
    from mbcal.language import load_model
    from mbcal.modeling import modeler, parameter_vector
    from mbcal.render.views import render_view, save_png
    from mbcal.workflows.demo import DEMO_TRUTH

    model_path = ROOT / "models" / "teleexistence.mdl"
    model = load_model(model_path)
    truth_scene = modeler(model, parameter_vector(model, DEMO_TRUTH))
    cams = {"p0": "robot.head.eyes.left", "p1": "robot.head.eyes.right"}
    for cam in cams.values():
        save_png(render_view(truth_scene, cam).color, tmp_path / f"{cam.split('.')[-1]}.png")
    out = tmp_path / "session"
    proc, url = _start_cli(
        [str(model_path), "--image", "eyes.left=left.png", "--image", "eyes.right=right.png", "--out", str(out)],
        tmp_path,
    )
    try:
        page = open_page(browser, url, 1900, 1150)
        page.wait_for_selector("svg[data-photo='p1'] .wire path", timeout=60_000)
        page.wait_for_function("() => (window.studio.solids || 0) >= 2", timeout=60_000)  # both translucent solids
        page.screenshot(path=str(images / "studio-start.png"))
        # 8 points in both photos: 16 pairs, at the true projections plus 1 px noise.
        points = [
            "room.valve.lever.hub",
            "room.valve.lever.tip",
            "room.upper_pipe.end_a",
            "room.upper_pipe.end_b",
            "room.lower_pipe.end_a",
            "room.lower_pipe.end_b",
            "room.gauge.center",
            "room.riser.end_a",
        ]
        rng = np.random.default_rng(12)
        n = 0
        for pid, cam in cams.items():
            view = truth_scene.camera(cam)
            for name in points:
                u, v = np.asarray(view.project(truth_scene.point(name))) + rng.normal(0.0, 1.0, 2)
                click_point(page, pid, name, float(u), float(v))
                n += 1
                page.wait_for_function("(n) => document.querySelectorAll('#clicks tbody tr').length === n", arg=n)
        page.fill("#estimate", "room.*")
        page.press("#estimate", "Enter")
        page.wait_for_selector("#sliders input[data-param='room.yaw']")
        page.click("#observe")
        page.wait_for_selector("#verdict")
        assert page.inner_text("#verdict").startswith("observable: rank 6 of 6")
        page.screenshot(path=str(images / "studio-clicked.png"))
        n, solids = page.evaluate("() => [window.studio.redraws, window.studio.solids || 0]")
        page.click("#solve")
        page.wait_for_selector("body[data-solved='1']", timeout=240_000)
        report = page.evaluate("() => window.studio.report")
        # The model is drawn at the estimate: wireframes, then both translucent solids.
        page.wait_for_function("(n) => window.studio.redraws > n", arg=n)
        page.wait_for_function("(n) => window.studio.solids >= n + 2", arg=solids, timeout=60_000)
        page.screenshot(path=str(images / "studio-solved.png"))
        page.select_option("#format", "csv")
        page.click("#save")
        page.wait_for_selector("body[data-saved]", timeout=120_000)
        page.close()
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    assert report["ok"], report["summary"]
    estimates = {p["name"]: p for p in report["params"]}
    assert set(estimates) == set(DEMO_TRUTH)
    for name, true in DEMO_TRUTH.items():
        est = estimates[name]
        assert abs(est["value"] - true) < 3 * est["std"], (name, est, true)
    for f in ["measurements.csv", "teleexistence_calibrated.mdl", "report.json", "studio-session.json"]:
        assert (out / f).is_file(), f
    assert list((out / "overlays").glob("*_after.png"))
    # The saved measurement file gives the same answer with `mbcal solve`.
    r = run_python(
        "-m", "mbcal", "solve", str(model_path), str(out / "measurements.csv"), "--estimate", "room.*",
        "--restarts", "16", "--json", str(tmp_path / "cli.json"), "-q",
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    cli = json.loads((tmp_path / "cli.json").read_text())["parameters"]
    for name, est in estimates.items():
        assert abs(cli[name]["value"] - est["value"]) < 1e-3 * est["std"], name
    # And the calibrated model carries the estimate as its nominal values.
    from mbcal.language import load_model as load

    calibrated = load(out / "teleexistence_calibrated.mdl")
    for name, est in estimates.items():
        assert abs(calibrated.param(name).nominal - est["value"]) < 1e-6 * max(1.0, abs(est["value"])) + 1e-9


# ---- Zhang's photograph ------------------------------------------------------------------------------


def _zhang_files():
    """His published intrinsics, distortion and view 1's R|t; his model and image corners."""
    nums = [float(x) for x in shared_data("zhang", "calibration-result-zhang-withdistortion.txt").read_text().split()]
    fx, skew, fy, cx, cy = nums[:5]
    k1, k2 = nums[5:7]
    R = np.array(nums[7:16]).reshape(3, 3)
    t = np.array(nums[16:19])
    model_xy = np.array([float(x) for x in shared_data("zhang", "Model.txt").read_text().split()]).reshape(-1, 2)
    image_uv = np.array([float(x) for x in shared_data("zhang", "data1.txt").read_text().split()]).reshape(-1, 2)
    return (fx, skew, fy, cx, cy, k1, k2), R, t, model_xy, image_uv


def test_zhangs_photograph_gives_his_published_pose_of_view_1(browser, images, tmp_path):
    from mbcal.geometry.transforms import rpy_from_matrix

    (fx, skew, fy, cx, cy, k1, k2), R, t, model_xy, image_uv = _zhang_files()
    # 8 corners spread over the board: the outer corners of the grid and 4 inside.
    picks = [0, 28, 227, 255, 66, 93, 162, 189]
    lines = [
        "# Zhang's target plane (his Model.txt, in his units), seen by his camera with his published",
        "# intrinsics and distortion as known values; the board's pose is the unknown.",
        "param board.x = -3.5 in [-8, 8]",
        "param board.y = 3.5 in [-8, 8]",
        "param board.z = 13 in [8, 20]",
        "param board.roll = 0 deg in [-30 deg, 30 deg]",
        "param board.pitch = 0 deg in [-30 deg, 30 deg]",
        "param board.yaw = 0 deg in [-30 deg, 30 deg]",
        f"camera cam(width = 640, height = 480, fx = {fx}, fy = {fy}, cx = {cx}, cy = {cy}, skew = {skew},",
        f"           k1 = {k1}, k2 = {k2})",
        "frame board at pose(board.x, board.y, board.z, board.roll, board.pitch, board.yaw) {",
        *(f"  point corner{i} = ({model_xy[i, 0]}, {model_xy[i, 1]}, 0)" for i in picks),
        # His 64 squares, drawn over the photo (each square's 4 corners are 4 rows of Model.txt).
        *(
            f"  shape square{k} = rectangle({np.ptp(sq[:, 0]):.6g}, {np.ptp(sq[:, 1]):.6g}) "
            f"at translate({sq[:, 0].mean():.6g}, {sq[:, 1].mean():.6g}, 0)"
            for k, sq in enumerate(model_xy.reshape(-1, 4, 2))
        ),
        "}",
        "measure image_point",
    ]
    model = tmp_path / "zhang.mdl"
    model.write_text("\n".join(lines) + "\n", encoding="utf-8")
    photo = shared_data("zhang", "CalibIm1.png")
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], tmp_path / "out")).start()
    try:
        page = open_page(browser, srv.url, 1700, 1100)
        page.wait_for_selector("svg[data-photo='p0'] .markers circle")
        page.wait_for_selector("svg[data-photo='p0'] .wire path[data-object='board']")
        for k, i in enumerate(picks):
            u, v = image_uv[i]
            click_point(page, "p0", f"board.corner{i}", float(u), float(v))
            page.wait_for_function("(n) => document.querySelectorAll('#clicks tbody tr').length === n", arg=k + 1)
        page.fill("#estimate", "board.*")
        page.press("#estimate", "Enter")
        page.fill("#restarts", "8")
        page.click("#solve")
        page.wait_for_selector("body[data-solved='1']", timeout=240_000)
        report = page.evaluate("() => window.studio.report")
        page.screenshot(path=str(images / "studio-zhang.jpg"), quality=80)
        page.close()
    finally:
        srv.stop()
    est = {p["name"]: p for p in report["params"]}
    roll, pitch, yaw = rpy_from_matrix(R)
    published = {"board.x": t[0], "board.y": t[1], "board.z": t[2], "board.roll": roll, "board.pitch": pitch,
                 "board.yaw": yaw}  # fmt: skip
    for name, value in published.items():
        assert abs(est[name]["value"] - value) < 3 * est[name]["std"], (name, est[name], value)
    # A wrong answer must not pass: the σ are those of 8 corners at 1 px, not huge.
    assert est["board.z"]["std"] < 0.1 and est["board.yaw"]["std"] < np.radians(0.5)


def test_the_slider_benchmark_writes_its_section_and_keeps_the_page(tmp_path):
    page = tmp_path / "performance.md"
    page.write_text("# Performance\n\nbench/run.py's part\n", encoding="utf-8")
    proc = run_python("bench/studio.py", "--moves", "3", "--out", str(page))
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = page.read_text(encoding="utf-8")
    assert text.startswith("# Performance\n\nbench/run.py's part\n")
    assert text.count("<!-- bench/studio.py: begin -->") == 1
    assert re.search(r"\| slider step → both overlays redrawn \(page, HTTP, server\) \| [0-9.]+ \|", text)


def test_the_printed_url_accepts_connections_at_once(tmp_path):
    """`mbcal studio` listens before it prints its URL: a browser opened on it at once (the
    default without --no-browser) is queued, not refused while the server starts up (CI saw
    ERR_CONNECTION_REFUSED)."""
    import socket
    import urllib.parse

    proc, url = _start_cli([str(ROOT / "models" / "teleexistence.mdl"), "--out", str(tmp_path / "s")], tmp_path)
    try:
        port = urllib.parse.urlsplit(url).port
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:  # no retry: at once
            conn.sendall(f"GET /?token=x HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n".encode())
            conn.settimeout(30)
            assert conn.recv(64).startswith(b"HTTP/1.1 ")  # served (a wrong token: 401/403, still an answer)
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_a_solve_edited_under_says_so_in_the_page_and_keeps_the_edit(browser, images, tmp_path, monkeypatch):
    """An edit while the solve runs: the page says the result is not used, keeps its values (the
    sliders are not moved to the stale estimate) and shows no report of it; a new solve clears it."""
    model = tmp_path / "small.mdl"
    model.write_text(SMALL, encoding="utf-8")
    out = tmp_path / "out"
    engine = Engine(model, [], [("cam", "default", _photo(tmp_path / "photo.png"))], out)
    engine.set_session(BLOCK_CLICKS, ["block.x", "block.y"], {}, [])
    release = _blocked_solve(monkeypatch)
    srv = StudioServer(engine).start()
    try:
        page = open_page(browser, srv.url, 1400, 900)
        page.wait_for_selector("svg[data-photo='p0'] .wire path")
        page.fill("#restarts", "2")
        page.click("#solve")
        page.wait_for_function("() => document.querySelector('#status').textContent.startsWith('solving')")
        page.fill("input[data-sigma='c0']", "0.5")  # an edit while it runs
        page.press("input[data-sigma='c0']", "Enter")
        _session_when(out, lambda s: s["clicks"][0]["sigma"] == 0.5)
        release.set()
        page.wait_for_selector("body[data-solved='stale']", timeout=120_000)
        assert page.is_visible("#stale") and "solve again" in page.inner_text("#stale")
        assert page.evaluate("() => window.studio.values") == {}
        assert page.inner_text("#estimates") == ""
        page.screenshot(path=str(images / "studio-stale.png"))
        page.click("#solve")  # solved again, unedited: adopted, and the notice goes
        page.wait_for_selector("body[data-solved='1']", timeout=120_000)
        assert not page.is_visible("#stale")
        assert set(page.evaluate("() => Object.keys(window.studio.values)")) == {"block.x", "block.y"}
        page.close()
    finally:
        srv.stop()
    assert engine.result is not None
