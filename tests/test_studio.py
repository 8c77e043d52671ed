"""The studio (``mbcal studio``): its server's security rules, the session kept on disk, model
errors and reloads — with a real uvicorn server and, for the page, Debian's Chromium driven by
Playwright (docs/studio.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

# The studio's server needs the studio extra (FastAPI, uvicorn), which the test extra includes:
# without it these tests fail at import instead of being skipped.
from mbcal.errors import MbcalError
from mbcal.studio.engine import Engine
from mbcal.studio.server import MAX_BODY, TOKEN_HEADER, StudioServer
from mbcal.studio.session import SESSION_FILE

SMALL = """\
param block.x = 0 m in [-10 cm, 10 cm]
param block.y = 0 m in [-10 cm, 10 cm]
param block.z = 2 m in [1.8 m, 2.2 m]
camera cam(width = 320, height = 240, fx = 300, fy = 300, cx = 159.5, cy = 119.5)
frame block at translate(block.x, block.y, block.z) {
  shape body = box(40 cm, 30 cm, 20 cm)
  point a = (-20 cm, -15 cm, -10 cm)
  point b = (20 cm, -15 cm, -10 cm)
  point c = (20 cm, 15 cm, -10 cm)
  point d = (-20 cm, 15 cm, -10 cm)
}
measure image_point
"""


def _photo(path: Path, width: int = 320, height: int = 240) -> Path:
    from PIL import Image

    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 255, (height, width, 3), dtype=np.uint8)).save(path)
    return path


@pytest.fixture
def small(tmp_path):
    """A small model, its photo and an output folder."""
    model = tmp_path / "small.mdl"
    model.write_text(SMALL, encoding="utf-8")
    return model, _photo(tmp_path / "photo.png"), tmp_path / "out"


@pytest.fixture
def server(small):
    model, photo, out = small
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    yield srv
    srv.stop()


def _session_when(out: Path, condition, timeout: float = 20.0) -> dict:
    """The session file once ``condition`` holds for it (the page saves asynchronously)."""
    import time

    end = time.monotonic() + timeout
    while True:
        doc = json.loads((out / SESSION_FILE).read_text())
        if condition(doc):
            return doc
        if time.monotonic() > end:
            raise AssertionError(f"the session file never reached the expected state: {doc}")
        time.sleep(0.05)


def _base(srv: StudioServer) -> str:
    return f"http://127.0.0.1:{srv.port}"


def _client(srv: StudioServer) -> httpx.Client:
    """A client that opened the page's URL and sends the token as the page does (a header)."""
    c = httpx.Client(timeout=30, headers={TOKEN_HEADER: srv.token})
    assert c.get(srv.url).status_code == 200
    return c


POST = {"Content-Type": "application/json"}


def test_the_token_is_required_in_the_url_or_the_header_and_never_set_as_a_cookie(server):
    base = _base(server)
    assert httpx.get(base + "/").status_code == 403
    assert httpx.get(base + "/api/state").status_code == 403
    assert httpx.get(base + "/?token=wrong").status_code == 403
    assert httpx.get(base + "/api/state", headers={TOKEN_HEADER: "wrong"}).status_code == 403
    r = httpx.get(server.url)
    assert r.status_code == 200 and "<title>mbcal studio</title>" in r.text
    # No cookie: a browser would send a 127.0.0.1 cookie to every other local port.
    assert "set-cookie" not in r.headers
    assert f'<meta name="studio-token" content="{server.token}">' in r.text
    assert f'src="/static/studio.js?token={server.token}"' in r.text
    assert httpx.get(base + f"/static/studio.js?token={server.token}").status_code == 200
    assert httpx.get(base + "/static/studio.js").status_code == 403
    c = _client(server)
    assert c.get(base + "/api/state").json()["model"] == "small.mdl"
    assert "frame-ancestors 'none'" in c.get(base + "/").headers["content-security-policy"]


def test_paths_from_the_page_are_never_opened(server, small):
    base = _base(server)
    c = _client(server)
    secret = small[0].resolve()
    for path in [
        "/static/../engine.py",
        "/static/..%2Fengine.py",
        "/api/photo/..%2F..%2Fsmall.mdl",
        "/api/photo/%2Fetc%2Fpasswd",
        f"/api/photo/{secret}",
        "/api/photo//etc/passwd",
        "/static/%2e%2e/server.py",
        "/api/photo/..\\small.mdl",
    ]:
        r = c.get(base + path)
        assert r.status_code in (400, 404), (path, r.status_code)
        assert "param block.x" not in r.text
    assert c.get(base + "/static/index.html").status_code == 404  # the page's files are a fixed list
    assert c.get(base + "/api/photo/p0").content[:4] == b"\x89PNG"
    origin = {"Origin": base, **POST}
    # A path where an id is expected is refused by the schema.
    for photo in ["/etc/passwd", "../small.mdl", str(secret)]:
        r = c.post(base + "/api/overlay", json={"photos": [photo]}, headers=origin)
        assert r.status_code == 422, photo
        r = c.post(base + "/api/solid", json={"photo": photo}, headers=origin)
        assert r.status_code == 422, photo
    bad_click = {"id": "c1", "camera": "cam", "config": "default", "point": "../../etc/passwd", "u": 1, "v": 2}
    r = c.post(base + "/api/session", json={"clicks": [bad_click]}, headers=origin)
    assert r.status_code == 422
    # The save format is an enum: no file name from the page.
    r = c.post(base + "/api/save", json={"format": "../../evil.csv"}, headers=origin)
    assert r.status_code == 422
    assert c.get(base + "/api/state").status_code == 200


def test_other_origins_hosts_oversized_and_malformed_bodies_are_refused(server):
    base = _base(server)
    c = _client(server)
    body = {"clicks": [], "estimate": ["block.*"]}
    assert (
        c.post(base + "/api/session", json=body, headers={"Origin": "http://evil.example", **POST}).status_code == 403
    )
    assert c.post(base + "/api/session", json=body, headers=POST).status_code == 403  # no Origin
    assert c.post(base + "/api/session", json=body, headers={"Origin": base, **POST}).status_code == 200
    r = c.get(base + "/api/state", headers={"Host": "attacker.example:80"})
    assert r.status_code == 403  # DNS rebinding: the Host must be the server's
    r = c.post(base + "/api/session", content=json.dumps(body), headers={"Origin": base, "Content-Type": "text/plain"})
    assert r.status_code == 415
    big = b'{"clicks": [], "estimate": ["' + b"x" * (MAX_BODY + 10) + b'"]}'
    r = c.post(base + "/api/session", content=big, headers={"Origin": base, **POST})
    assert r.status_code == 413
    r = c.post(base + "/api/session", content=b'{"clicks": [', headers={"Origin": base, **POST})
    assert r.status_code == 422 and "invalid request" in r.json()["error"]["message"]
    r = c.post(base + "/api/session", json={"clicks": [], "extra": 1}, headers={"Origin": base, **POST})
    assert r.status_code == 422
    nan_click = {"id": "c1", "camera": "cam", "config": "default", "point": "block.a", "u": "NaN", "v": 2}
    r = c.post(base + "/api/session", json={"clicks": [nan_click]}, headers={"Origin": base, **POST})
    assert r.status_code == 422
    r = c.post(
        base + "/api/session",
        json={"clicks": [{**nan_click, "u": 1, "point": "block.zz"}]},
        headers={"Origin": base, **POST},
    )
    assert r.status_code == 400 and "no point 'block.zz'" in r.json()["error"]["message"]
    assert c.get(base + "/api/state").status_code == 200  # still up


def test_edits_are_saved_at_once_and_survive_a_restart(small):
    model, photo, out = small
    click = {"id": "c1", "camera": "cam", "config": "default", "point": "block.a", "u": 129.5, "v": 97.0, "sigma": 0.5}
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        c = _client(srv)
        r = c.post(
            _base(srv) + "/api/session",
            json={"clicks": [click], "estimate": ["block.*"], "values": {"block.x": 0.01}},
            headers={"Origin": _base(srv), **POST},
        )
        assert r.status_code == 200
        saved = json.loads((out / SESSION_FILE).read_text())
        assert saved["clicks"][0]["u"] == 129.5 and saved["estimate"] == ["block.*"]
    finally:
        srv.stop()
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        state = _client(srv).get(_base(srv) + "/api/state").json()
        assert state["session"]["clicks"] == [click]
        assert state["session"]["values"] == {"block.x": 0.01}
    finally:
        srv.stop()


def test_the_studio_without_its_extra_says_how_to_install_it():
    # A Python where fastapi is not found.
    code = (
        "import importlib.util, sys\n"
        "real = importlib.util.find_spec\n"
        "importlib.util.find_spec = lambda n, *a: None if n == 'fastapi' else real(n, *a)\n"
        "from mbcal.cli import main\n"
        "sys.exit(main(['studio', 'models/teleexistence.mdl', '--no-browser']))\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1]
    )
    assert r.returncode == 2
    assert "pip install 'mbcal[studio]'" in r.stderr
    assert "Traceback" not in r.stderr


# ---- the page, in Chromium ------------------------------------------------------------------------------


def open_page(browser, url: str, width: int = 1600, height: int = 1000):
    page = browser.new_page(viewport={"width": width, "height": height})
    page.goto(url)
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    assert "token=" not in page.url  # dropped from the address and the history; the page keeps it
    return page


def click_point(page, photo: str, point: str, u: float, v: float) -> None:
    """Pick ``point`` by searching its name, then click (u, v) of the photo with the mouse."""
    page.fill("#search", point)
    page.press("#search", "Enter")
    page.wait_for_selector(f"#pointlist li.armed[data-point='{point}']")
    x, y = page.evaluate("([p, u, v]) => window.studio.toClient(p, u, v)", [photo, u, v])
    page.mouse.click(x, y)
    page.wait_for_function("(n) => document.querySelectorAll('#clicks tbody tr').length >= n", arg=1)


@pytest.mark.slow
def test_clicks_in_the_page_survive_a_restart_and_a_model_reload(browser, small):
    model, photo, out = small
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        page = open_page(browser, srv.url)
        page.wait_for_selector("svg[data-photo='p0'] .wire path")
        click_point(page, "p0", "block.a", 110.25, 80.5)
        click_point(page, "p0", "block.b", 210.0, 81.0)
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 2")
        _session_when(out, lambda s: len(s["clicks"]) == 2)
        page.close()
    finally:
        srv.stop()
    saved = json.loads((out / SESSION_FILE).read_text())["clicks"]
    assert [c["point"] for c in saved] == ["block.a", "block.b"]
    # The mouse puts the click where it was asked to, to a small fraction of a pixel.
    assert abs(saved[0]["u"] - 110.25) < 0.15 and abs(saved[0]["v"] - 80.5) < 0.15
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        page = open_page(browser, srv.url)
        rows = page.locator("#clicks tbody tr")
        assert rows.count() == 2
        # the point cell (the 4th) names the saved clicks' points, in their order
        assert [rows.nth(i).locator("td").nth(3).get_attribute("title") for i in range(2)] == ["block.a", "block.b"]
        # Undo and redo with the keyboard; delete with the Delete key.
        page.click("#clicks tbody tr[data-click='c2'] td")
        page.keyboard.press("Delete")
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 1")
        page.keyboard.press("Control+z")
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 2")
        page.keyboard.press("Control+y")
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 1")
        page.keyboard.press("Control+z")
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 2")
        # The model changes: point b is renamed; a reload keeps a, drops b and says so.
        model.write_text(SMALL.replace("point b =", "point b2 ="), encoding="utf-8")
        page.click("#reload")
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 1")
        assert "dropped" in page.inner_text("#notes")
        page.close()
    finally:
        srv.stop()
    assert [c["point"] for c in json.loads((out / SESSION_FILE).read_text())["clicks"]] == ["block.a"]


@pytest.mark.slow
def test_a_model_error_is_shown_in_the_page_and_the_server_stays_up(browser, small):
    model, photo, out = small
    model.write_text(SMALL.replace("box(40 cm, 30 cm, 20 cm)", "box(40 cm, 30 cm, 20 kg)"), encoding="utf-8")
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        page = open_page(browser, srv.url)
        assert page.is_visible("#error")
        location = page.inner_text("#error-location")
        assert f"{model}:6:" in location
        assert "box(40 cm, 30 cm, 20 kg)" in page.inner_text("#error-source")
        assert "^" in page.inner_text("#error-source")
        assert _client(srv).get(_base(srv) + "/api/state").status_code == 200
        model.write_text(SMALL, encoding="utf-8")
        page.click("#reload")
        page.wait_for_selector("#error", state="hidden")
        page.wait_for_selector("svg[data-photo='p0'] .wire path")
        page.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_the_page_tools_solid_opacity_objects_loupe_drag_zoom_observe_configurations(browser, small, tmp_path):
    model, photo, out = small
    photo2 = _photo(tmp_path / "photo2.png")
    srv = StudioServer(Engine(model, [], [("cam", "default", photo), ("cam", "pose2", photo2)], out)).start()
    try:
        page = open_page(browser, srv.url)
        page.wait_for_selector("svg[data-photo='p0'] .wire path[data-object='block']")
        assert page.locator(".view").count() == 1  # one configuration at a time
        # The translucent solid, rendered by the server, arrives.
        page.wait_for_selector("svg[data-photo='p0'] image.solid[data-loaded='1']", state="attached")
        # Opacity slider and per-object toggle.
        page.eval_on_selector("#opacity", "e => { e.value = 0.25; e.dispatchEvent(new Event('input')); }")
        assert page.get_attribute("svg[data-photo='p0'] g.overlay", "opacity") == "0.25"
        page.uncheck("input[data-object='block']")
        assert page.eval_on_selector("path[data-object='block']", "e => e.style.display") == "none"
        page.check("input[data-object='block']")
        # The loupe follows the mouse over a photo.
        x, y = page.evaluate("() => window.studio.toClient('p0', 100, 100)")
        page.mouse.move(x, y)
        page.wait_for_selector("#loupe", state="visible")
        assert "100.0" in page.inner_text("#loupe") or "99.9" in page.inner_text("#loupe")
        # A refused action says why in the page, until the next action succeeds.
        page.click("#observe")
        page.wait_for_selector("#error", state="visible")
        assert "choose the unknowns first" in page.inner_text("#error-location")
        # Pick by clicking the marker, then the photo; then drag the click to a better place.
        a = page.evaluate("() => window.studio.views.p0.proj.points.find(p => p.name === 'block.a')")
        mx, my = page.evaluate("([u, v]) => window.studio.toClient('p0', u, v)", [a["u"], a["v"]])
        page.mouse.click(mx, my)
        page.wait_for_selector("#pointlist li.armed[data-point='block.a']")
        x, y = page.evaluate("() => window.studio.toClient('p0', 80, 60)")
        page.mouse.click(x, y)
        page.wait_for_function("() => document.querySelectorAll('#clicks tbody tr').length === 1")
        page.wait_for_selector("#error", state="hidden")
        x2, y2 = page.evaluate("() => window.studio.toClient('p0', 90.5, 65.25)")
        page.mouse.move(x, y)
        page.mouse.down()
        page.mouse.move((x + x2) / 2, (y + y2) / 2)
        page.mouse.move(x2, y2)
        page.mouse.up()
        page.wait_for_function("() => window.studio.clicks[0].u > 89")
        saved = _session_when(out, lambda s: s["clicks"] and s["clicks"][0]["u"] > 89)["clicks"][0]
        assert abs(saved["u"] - 90.5) < 0.15 and abs(saved["v"] - 65.25) < 0.15
        # σ is edited in the measurement table.
        page.fill("input[data-sigma='c1']", "0.4")
        page.press("input[data-sigma='c1']", "Enter")
        assert _session_when(out, lambda s: s["clicks"][0]["sigma"] != 1.0)["clicks"][0]["sigma"] == 0.4
        # Observe: one click cannot fix three unknowns; the page says so and marks points to click next.
        page.fill("#estimate", "block.*")
        page.press("#estimate", "Enter")
        page.wait_for_selector("#sliders input[data-param='block.z']")
        page.click("#observe")
        page.wait_for_selector("#verdict")
        assert page.inner_text("#verdict").startswith("NOT observable")
        page.wait_for_selector("svg[data-photo='p0'] .marker.suggested")
        # A coarse-alignment slider moves the overlay.
        before = page.get_attribute("path[data-object='block']", "d")
        n = page.evaluate("() => window.studio.redraws")
        page.focus("#sliders input[data-param='block.x']")
        page.keyboard.press("PageUp")
        page.wait_for_function("(n) => window.studio.redraws > n", arg=n)
        assert page.get_attribute("path[data-object='block']", "d") != before
        # Zoom with the wheel.
        box = page.get_attribute("svg[data-photo='p0']", "viewBox")
        page.mouse.move(x, y)
        page.mouse.wheel(0, -300)
        page.wait_for_function(
            "(b) => document.querySelector(\"svg[data-photo='p0']\").getAttribute('viewBox') !== b", arg=box
        )
        # The parameter tree: unchecking one unknown of a glob keeps the others.
        page.click("#param-tree summary")  # the 'block' group is open: it holds chosen unknowns
        assert page.is_checked("input[data-estimate='block.z']")
        page.uncheck("input[data-estimate='block.z']")
        page.wait_for_function("() => window.studio.estimate.join(',') === 'block.x,block.y'")
        assert page.locator("#sliders input[data-param='block.z']").count() == 0
        # Another configuration shows its own photo.
        page.select_option("#config", "pose2")
        page.wait_for_selector("svg[data-photo='p1'] .wire path")
        assert page.locator("svg[data-photo='p0']").count() == 0
        page.close()
    finally:
        srv.stop()


@pytest.mark.slow
def test_bad_command_lines_get_a_clear_message_and_status_2(tmp_path):
    root = Path(__file__).resolve().parents[1]
    cases = [
        (["--image", "eyes.left"], "--image expects CAMERA=PHOTO"),
        (["--image", f"eyes.left={tmp_path / 'missing.png'}"], "photo not found"),
        (["--out", str(root / "README.md")], "is a file"),
        (["missing.csv"], "file not found: missing.csv"),
        (["--image", f"nocam={_photo(tmp_path / 'p.png')}"], "the model's cameras: robot.head.eyes.left"),
    ]
    for extra, message in cases:
        r = subprocess.run(
            [sys.executable, "-m", "mbcal", "studio", "models/teleexistence.mdl", *extra, "--no-browser"],
            capture_output=True,
            text=True,
            cwd=root,
            timeout=120,
        )
        assert r.returncode == 2, (extra, r.stderr)
        assert message in r.stderr and "Traceback" not in r.stderr, r.stderr


def _no_serving(monkeypatch) -> None:
    """``mbcal studio`` in-process must be refused before it serves: serving fails the test, not hangs it."""
    from mbcal.studio import server as studio_server

    def serve(engine, host, port, **_kwargs):
        StudioServer(engine, host, port).sock.close()  # its refusals, as the real one
        raise AssertionError("the studio started serving")

    monkeypatch.setattr(studio_server, "serve_forever", serve)


def test_a_camera_the_model_lacks_is_the_command_lines_error_at_start_and_the_models_on_reload(
    small, capsys, monkeypatch
):
    from mbcal import cli

    model, photo, out = small
    _no_serving(monkeypatch)
    assert cli.main(["studio", str(model), "--image", f"left={photo}", "--no-browser", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--image left={photo}: the model has no camera named 'left' (the model's cameras: cam)" in err
    assert "the model has an error" not in err
    assert cli.main(["studio", str(model), "--image", f"cma@pose2={photo}", "--no-browser", "--out", str(out)]) == 2
    assert "--image cma@pose2=" in (err := capsys.readouterr().err) and "did you mean 'cam'?" in err
    # On a reload the camera is the model's to fix: shown in the page, the server goes on.
    engine = Engine(model, [], [("cam", "default", photo)], out)
    model.write_text(SMALL.replace("camera cam(", "camera eye("), encoding="utf-8")
    r = engine.reload()
    assert not r["ok"] and r["error"]["message"].startswith("--image cam=")
    model.write_text(SMALL, encoding="utf-8")
    assert engine.reload()["ok"]


def test_a_broken_measurement_file_is_named_at_start_and_its_clicks_come_at_reload(small, capsys, monkeypatch):
    """`mbcal studio MODEL bad.csv` said "the model has an error" for the measurement file's, and
    the file's clicks never came: the empty session saved at start was restored ever after.  It
    starts as with a broken model (the error shown in the page), naming the file to fix; the
    file's clicks are taken at the Reload that reads it."""
    from mbcal import cli
    from mbcal.studio import server as studio_server

    model, photo, out = small
    bad = model.parent / "clicks.csv"
    bad.write_text("x\n", encoding="utf-8")
    served: list[Engine] = []
    monkeypatch.setattr(studio_server, "serve_forever", lambda engine, *a, **k: served.append(engine) or 0)
    assert cli.main(["studio", str(model), str(bad), "--image", f"cam={photo}", "--no-browser", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"mbcal studio: the measurement file {bad} has an error (shown in the page too):\n{bad}:1:1:" in err
    assert "the model has an error" not in err
    (engine,) = served
    assert engine.state()["error"]["what"] == f"the measurement file {bad}"
    with pytest.raises(MbcalError, match=f"the measurement file {bad} did not load \\({bad}:1:1\\)"):
        engine.require_model()
    assert not (out / SESSION_FILE).exists()  # a restart reads the file's clicks, once it is fixed
    bad.write_text("id,kind,config,camera,point,u,v,sigma\nk1,image_point,default,cam,block.a,100,120,1\n")
    r = engine.reload()
    assert r["ok"] and r["error"] is None
    assert [(c.id, c.point) for c in engine.session.clicks] == [("k1", "block.a")]
    assert [c["point"] for c in json.loads((out / SESSION_FILE).read_text())["clicks"]] == ["block.a"]


def test_the_page_ships_inside_the_package():
    from importlib import resources

    static = resources.files("mbcal.studio").joinpath("static")
    for name in ("index.html", "studio.js", "studio.css"):
        assert static.joinpath(name).is_file(), name
    assert "/static/studio.js" in static.joinpath("index.html").read_text(encoding="utf-8")


@pytest.mark.slow
def test_each_configuration_is_drawn_with_its_own_joint_readings(tmp_path):
    """The arm in two attitudes (joint readings from a measurement file), one photo each: each
    photo's overlay is the model at its configuration's readings, and a per-configuration estimate
    (name@config) moves only its own configuration's overlay."""
    from mbcal.language import load_model
    from mbcal.measurements.io import read_measurements
    from mbcal.modeling import modeler, parameter_vector

    root = Path(__file__).resolve().parents[1]
    model_path, plan = root / "models" / "arm7.mdl", root / "measurements" / "arm_plan.json"
    model = load_model(model_path)
    readings = read_measurements(plan, model).configurations
    photos = [("eyes.left", cfg, _photo(tmp_path / f"{cfg}.png", 669, 453)) for cfg in ("pose01", "pose02")]
    engine = Engine(model_path, [plan], photos, tmp_path / "out")
    assert {"pose01", "pose02"} <= set(engine.configurations())
    assert engine.session.clicks == []  # a plan has no values: nothing to click yet
    point = next(p.name for p in model.points if "arm" in p.name)
    for pid, (_, cfg, _) in zip(["p0", "p1"], photos):
        proj = engine.projection(pid)
        scene = modeler(model, parameter_vector(model, readings[cfg]))
        expected = np.asarray(scene.camera("eyes.left").project(scene.point(point)))
        got = next(p for p in proj["points"] if p["name"] == point)
        assert abs(got["u"] - expected[0]) < 1e-2 and abs(got["v"] - expected[1]) < 1e-2
    before = [engine.projection(pid)["paths"] for pid in ("p0", "p1")]
    engine.set_session([], ["arm.offset*"], {"torso.q@pose02": readings["pose02"]["torso.q"] + 0.05}, [])
    after = [engine.projection(pid)["paths"] for pid in ("p0", "p1")]
    assert after[0] == before[0] and after[1] != before[1]


def _tenths_points(paths: dict) -> np.ndarray:
    xy = [np.asarray(flat, dtype=float).reshape(-1, 2) / 10 for groups in paths.values() for _, flat in groups]
    return np.concatenate(xy) if xy else np.zeros((0, 2))


def test_hidden_edges_are_left_out_of_the_wireframe(small):
    """A box seen face on: with occlusion only its front face's outline is drawn; without, the
    back face's edges (inside that outline) are drawn too."""
    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    du, dv = 300 * 0.2 / 1.9, 300 * 0.15 / 1.9  # the front face (z = 1.9 m) in pixels
    every = _tenths_points(engine.projection("p0", occlusion=False)["paths"])
    seen = _tenths_points(engine.projection("p0", occlusion=True)["paths"])
    assert len(seen) < len(every)
    front = (np.abs(np.abs(seen[:, 0] - 159.5) - du) < 0.15) | (np.abs(np.abs(seen[:, 1] - 119.5) - dv) < 0.15)
    inside = (np.abs(seen[:, 0] - 159.5) <= du + 0.15) & (np.abs(seen[:, 1] - 119.5) <= dv + 0.15)
    assert np.all(front & inside)
    back_corner = [159.5 + 300 * 0.2 / 2.1, 119.5 + 300 * 0.15 / 2.1]
    assert np.min(np.linalg.norm(every - back_corner, axis=1)) < 0.15
    assert np.min(np.linalg.norm(seen - back_corner, axis=1)) > 2.0
    points = {p["name"]: p for p in engine.projection("p0")["points"]}
    assert not any(p["hidden"] for p in points.values())  # the named points are on the front face


# ---- from a security review: no cookie, no token in argv or history, writes only under --out


def test_two_studios_keep_their_tokens_and_odd_tokens_are_refused_not_crashed(small, tmp_path):
    model, photo, out = small
    a = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    b = StudioServer(Engine(model, [], [("cam", "default", photo)], tmp_path / "out2")).start()
    try:
        assert _client(a).get(_base(a) + "/api/state").status_code == 200
        assert _client(b).get(_base(b) + "/api/state").status_code == 200
        assert httpx.get(_base(a) + "/api/state", headers={TOKEN_HEADER: b.token}).status_code == 403
        for odd in ("%C3%A9", "%00", "x" * 5000):
            assert httpx.get(_base(a) + f"/api/state?token={odd}").status_code == 403
        assert httpx.get(_base(a) + "/api/state", headers={TOKEN_HEADER: "é".encode()}).status_code == 403
    finally:
        a.stop()
        b.stop()


def test_the_browser_is_opened_on_a_private_redirect_file_not_on_the_token(small, monkeypatch):
    import webbrowser

    from mbcal.studio import server as studio_server

    opened = []
    monkeypatch.setattr(webbrowser, "open", opened.append)
    _model, _photo_path, out = small
    out.mkdir()
    url = "http://127.0.0.1:5/?token=SECRET"
    path = studio_server._open_browser(url, out)
    assert opened == [path.as_uri()] and "SECRET" not in opened[0]  # argv names a file
    assert path.stat().st_mode & 0o777 == 0o600
    assert 'content="0; url=http://127.0.0.1:5/?token=SECRET"' in path.read_text()


def test_wildcard_hosts_and_ports_out_of_range_are_refused_before_anything_is_written(small, tmp_path):
    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    for host in ("0.0.0.0", "::"):
        with pytest.raises(MbcalError, match="every address"):
            StudioServer(engine, host=host)
    with pytest.raises(MbcalError, match="65535"):
        StudioServer(engine, port=70000)
    r = subprocess.run(
        [sys.executable, "-m", "mbcal", "studio", str(model), "--out", str(tmp_path / "o"), "--port", "70000"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "--port: expected a port from 0" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


def test_a_refused_start_says_only_why_and_leaves_no_folder(small, tmp_path, capsys, monkeypatch):
    import mbcal.studio.engine as studio_engine
    from mbcal import cli

    model, photo, _out = small
    _no_serving(monkeypatch)
    out = tmp_path / "a" / "b" / "out"
    for extra, message in [
        (["--host", "0.0.0.0", "--image", f"cam={photo}"], "--host 0.0.0.0 listens on every address"),
        (["--image", f"cam={tmp_path / 'nothere.png'}"], "photo not found"),
        (["--image", f"left={photo}"], "--image left="),
    ]:
        assert cli.main(["studio", str(model), *extra, "--no-browser", "--out", str(out)]) == 2, extra
        err = capsys.readouterr().err
        assert message in err and "warning" not in err, (extra, err)  # refused: no warning about the host first
        assert not (tmp_path / "a").exists(), extra

    # The session cannot be written (a full disk): the folders made for it are removed again.
    def full(*_args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(studio_engine, "save_session", full)
    with pytest.raises(MbcalError, match="cannot save the session"):
        Engine(model, [], [("cam", "default", photo)], out)
    assert not (tmp_path / "a").exists()


def test_save_writes_only_under_out_and_never_over_a_photo(small, tmp_path):
    model, photo, out = small
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    engine = Engine(model, [], [("cam", "default", photo)], out)
    click = {"id": "c1", "camera": "cam", "config": "default", "point": "block.a", "u": 10.0, "v": 20.0, "sigma": 1.0}
    engine.set_session([click], ["block.*"], {}, [])
    (out / "measurements.csv").symlink_to(elsewhere / "victim.csv")
    with pytest.raises(MbcalError, match="writes only under --out"):
        engine.save("csv")
    assert list(elsewhere.iterdir()) == []
    (out / "measurements.csv").unlink()
    (out / "overlays").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(MbcalError, match="writes only under --out"):
        engine._target_path("overlays")
    # A photo where Save draws its overlays is refused when the studio starts.
    (out / "overlays").unlink()
    (out / "overlays").mkdir()
    inside = _photo(out / "overlays" / "cam_after.png")
    with pytest.raises(MbcalError, match="which Save writes into"):
        Engine(model, [], [("cam", "default", inside)], tmp_path / "out3" / ".." / "out")


def test_another_models_session_in_out_is_kept_not_replaced(small, tmp_path):
    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    engine.set_session([{"id": "c1", "camera": "cam", "config": "default", "point": "block.a", "u": 10.0,
                         "v": 20.0, "sigma": 1.0}], ["block.*"], {}, [])  # fmt: skip
    before = (out / SESSION_FILE).read_text()
    other = tmp_path / "other.mdl"
    other.write_text(SMALL.replace("point a", "point e"), encoding="utf-8")
    with pytest.raises(MbcalError, match="holds a session of"):
        Engine(other, [], [("cam", "default", photo)], out)
    assert (out / SESSION_FILE).read_text() == before
    assert json.loads(before)["model"] == str(model.resolve())


def test_an_edit_after_a_solve_keeps_its_result_out_of_the_save(small):
    import time

    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    clicks = [
        {"id": f"c{i}", "camera": "cam", "config": "default", "point": f"block.{name}", "u": u, "v": v, "sigma": 1.0}
        for i, (name, u, v) in enumerate(
            [("a", 130.0, 97.0), ("b", 190.0, 97.0), ("c", 190.0, 142.0), ("d", 130.0, 142.0)]
        )
    ]
    engine.set_session(clicks, ["block.x", "block.y"], {}, [])
    engine.start_solve(restarts=2)
    end = time.monotonic() + 120
    while not engine.solve_status()["done"] and time.monotonic() < end:
        time.sleep(0.05)
    assert engine.result is not None, engine.solve_status()
    engine.set_session(clicks, ["block.x", "block.y"], {}, [])  # the same clicks: the result stands
    assert engine.result is not None
    moved = [dict(c, u=c["u"] + 50.0) if c["id"] == "c0" else c for c in clicks]
    engine.set_session(moved, ["block.x", "block.y"], {}, [])
    assert engine.result is None  # solved from other clicks: not saved beside these
    saved = engine.save("csv")
    assert saved["written"] == ["measurements.csv"] and not (out / "report.json").exists()
    assert saved["earlier"] == [] and not any("earlier Save" in note for note in saved["notes"])
    # A Save of the solved clicks, then an edit and a Save: the earlier report stays (nothing is
    # removed unasked) and the answer, shown on the page, says it is of other clicks.
    engine.set_session(clicks, ["block.x", "block.y"], {}, [])
    engine.start_solve(restarts=2)
    _solved(engine)
    assert engine.save("csv")["written"][:3] == ["measurements.csv", "small_calibrated.mdl", "report.json"]
    engine.set_session(moved, ["block.x", "block.y"], {}, [])
    saved = engine.save("csv")
    assert saved["written"] == ["measurements.csv"] and (out / "report.json").exists()
    assert saved["earlier"][:2] == ["small_calibrated.mdl", "report.json"]
    assert any("from an earlier Save, of other clicks" in note for note in saved["notes"])


def _blocked_solve(monkeypatch):
    """The engine's solver held until the returned event is set: an edit lands while it runs."""
    import threading

    import mbcal.studio.engine as studio_engine

    release = threading.Event()
    real = studio_engine.calibrate

    def held(*args, **kwargs):
        assert release.wait(timeout=120)
        return real(*args, **kwargs)

    monkeypatch.setattr(studio_engine, "calibrate", held)
    return release


def _solved(engine: Engine, timeout: float = 120.0) -> dict:
    import time

    end = time.monotonic() + timeout
    while not engine.solve_status()["done"]:
        assert time.monotonic() < end, "the solve did not finish"
        time.sleep(0.05)
    return engine.solve_status()


BLOCK_CLICKS = [
    {"id": f"c{i}", "camera": "cam", "config": "default", "point": f"block.{name}", "u": u, "v": v, "sigma": 1.0}
    for i, (name, u, v) in enumerate([("a", 130.0, 97.0), ("b", 190.0, 97.0), ("c", 190.0, 142.0), ("d", 130.0, 142.0)])
]


def test_a_solve_that_finishes_after_an_edit_is_stale_not_saved_and_keeps_the_new_values(small, monkeypatch):
    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    engine.set_session(BLOCK_CLICKS, ["block.x", "block.y"], {}, [])
    release = _blocked_solve(monkeypatch)
    engine.start_solve(restarts=2)
    # The operator corrects every click by 3 px and moves a slider while the solve runs.
    moved = [dict(c, u=c["u"] + 3.0) for c in BLOCK_CLICKS]
    engine.set_session(moved, ["block.x", "block.y"], {"block.x": 0.02}, [])
    release.set()
    status = _solved(engine)
    assert status["error"] is None and status["stale"] and "report" not in status
    assert engine.result is None  # not the current result: Save must not write it beside the new clicks
    assert engine.session.values == {"block.x": 0.02}  # the operator's value, not the solve's
    saved = json.loads((out / SESSION_FILE).read_text())
    assert saved["values"] == {"block.x": 0.02} and saved["clicks"][0]["u"] == 133.0
    assert engine.save("csv")["written"] == ["measurements.csv"]
    assert not (out / "report.json").exists() and not (out / "small_calibrated.mdl").exists()
    # Solved again, unedited: the result is adopted.
    engine.start_solve(restarts=2)
    status = _solved(engine)
    assert not status["stale"] and status["report"]["params"]
    assert engine.result is not None and set(engine.session.values) == {"block.x", "block.y"}


def _flat_photo(path: Path, rgb: tuple[int, int, int], width: int = 320, height: int = 240) -> Path:
    from PIL import Image

    Image.new("RGB", (width, height), rgb).save(path)
    return path


def _median_colour(path: Path) -> list[float]:
    from PIL import Image

    with Image.open(path) as img:
        return np.median(np.asarray(img.convert("RGB")).reshape(-1, 3), axis=0).tolist()


def test_each_configurations_overlays_are_drawn_on_its_own_photo(small, tmp_path):
    """One camera in two configurations, a red photo and a blue one: Save draws each
    configuration's before/after overlays over its own photo, not every one over the last."""
    model, _photo_path, out = small
    red = _flat_photo(tmp_path / "red.png", (255, 0, 0))
    blue = _flat_photo(tmp_path / "blue.png", (0, 0, 255))
    engine = Engine(model, [], [("cam", "default", red), ("cam", "pose2", blue)], out)
    clicks = BLOCK_CLICKS + [dict(c, id=f"p2{c['id']}", config="pose2", v=c["v"] + 1.0) for c in BLOCK_CLICKS]
    engine.set_session(clicks, ["block.x", "block.y"], {}, [])
    engine.start_solve(restarts=2)
    assert _solved(engine)["error"] is None
    written = engine.save("csv")["written"]
    assert {w for w in written if w.startswith("overlays/")} == {
        "overlays/cam_before.png", "overlays/cam_after.png",
        "overlays/cam_pose2_before.png", "overlays/cam_pose2_after.png",
    }  # fmt: skip
    for name in ("cam_before", "cam_after"):
        assert _median_colour(out / "overlays" / f"{name}.png") == [255, 0, 0], name
    for name in ("cam_pose2_before", "cam_pose2_after"):
        assert _median_colour(out / "overlays" / f"{name}.png") == [0, 0, 255], name


def test_save_checks_every_file_before_writing_any(small, tmp_path):
    model, photo, out = small
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    engine = Engine(model, [], [("cam", "default", photo)], out)
    engine.set_session(BLOCK_CLICKS, ["block.x", "block.y"], {}, [])
    engine.start_solve(restarts=2)
    assert _solved(engine)["error"] is None
    (out / "report.json").symlink_to(elsewhere / "report.json")
    with pytest.raises(MbcalError, match="writes only under --out"):
        engine.save("json")
    assert sorted(p.name for p in out.iterdir()) == ["report.json", SESSION_FILE]  # nothing written
    assert list(elsewhere.iterdir()) == []
    (out / "report.json").unlink()
    (out / "overlays").mkdir()
    (out / "overlays" / "cam_after.png").symlink_to(elsewhere / "cam_after.png")
    with pytest.raises(MbcalError, match="writes only under --out"):
        engine.save("json")
    assert sorted(p.name for p in out.iterdir()) == ["overlays", SESSION_FILE]
    (out / "overlays" / "cam_after.png").unlink()
    saved = engine.save("json")
    assert saved["written"][:3] == ["measurements.json", "small_calibrated.mdl", "report.json"]
    assert saved["earlier"] == []
    # a Save in the other format leaves the first file and names it as an earlier Save's
    saved = engine.save("csv")
    assert saved["earlier"] == ["measurements.json"] and (out / "measurements.json").exists()
    assert any("measurements.json" in note and "earlier Save" in note for note in saved["notes"])


def test_a_save_removes_the_overlays_an_earlier_save_drew_and_this_one_does_not(small, tmp_path, monkeypatch):
    import mbcal.render.overlays as overlays

    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo), ("cam", "pose2", _photo(tmp_path / "p2.png"))], out)
    both = BLOCK_CLICKS + [dict(c, id=f"p2{c['id']}", config="pose2") for c in BLOCK_CLICKS]
    engine.set_session(both, ["block.x", "block.y"], {}, [])
    engine.start_solve(restarts=2)
    assert _solved(engine)["error"] is None
    engine.save("csv")
    mine = _photo(out / "overlays" / "mine_after.png")  # the operator's own file: never the studio's to remove
    engine.set_session(BLOCK_CLICKS, ["block.x", "block.y"], {}, [])  # pose2's clicks deleted
    engine.start_solve(restarts=2)
    assert _solved(engine)["error"] is None
    saved = engine.save("csv")
    assert sorted(p.name for p in (out / "overlays").iterdir() if not p.name.startswith(".")) == [
        "cam_after.png", "cam_before.png", mine.name
    ]  # fmt: skip
    assert saved["removed"] == ["overlays/cam_pose2_after.png", "overlays/cam_pose2_before.png"]
    # The overlays fail half-way: none of this Save's is kept, the earlier ones (of another solve) go,
    # and the measurements, the model and the report are still saved.
    drawn = overlays.calibration_overlays

    def half(result, folder, **kwargs):
        drawn(result, folder, **kwargs)
        raise MbcalError("no OpenGL context")

    monkeypatch.setattr(overlays, "calibration_overlays", half)
    (out / "report.json").unlink()
    saved = engine.save("csv")
    assert saved["written"] == ["measurements.csv", "small_calibrated.mdl", "report.json"]
    assert saved["removed"] == ["overlays/cam_after.png", "overlays/cam_before.png"]
    assert "overlays not drawn: no OpenGL context" in engine.notes
    assert (out / "report.json").is_file() and not (out / "overlays" / "cam_after.png").exists()
    assert mine.exists() and not list((out / "overlays").glob(".*.part"))


def test_imported_ids_stay_unique_and_configuration_names_are_checked(small, tmp_path):
    model, photo, out = small
    clicks = tmp_path / "clicks.json"
    clicks.write_text(
        json.dumps(
            {
                "measurements": [
                    {"id": "a/1", "kind": "image_point", "camera": "cam", "point": "block.a", "u": 10, "v": 20},
                    {"id": "a_1", "kind": "image_point", "camera": "cam", "point": "block.b", "u": 30, "v": 40},
                ]
            }
        )
    )
    engine = Engine(model, [clicks], [("cam", "default", photo)], out)
    ids = [c.id for c in engine.session.clicks]
    assert sorted(ids) == ["a_1", "a_1_2"]
    assert engine.save("csv")["written"] == ["measurements.csv"]  # no duplicate ids
    with pytest.raises(MbcalError, match="configuration name 'pose/1'"):
        Engine(model, [], [("cam", "pose/1", photo)], tmp_path / "out2")


def test_imported_sigmas_of_u_and_v_are_kept_through_the_session_the_solve_and_save(small, tmp_path):
    from mbcal.language import load_model
    from mbcal.measurements.io import read_measurements

    model, photo, out = small
    given = tmp_path / "aniso.csv"
    given.write_text(
        "id,kind,config,camera,point,u,v,sigma_u,sigma_v\n"
        "m1,image_point,default,cam,block.a,130,97,0.5,3.0\n"
        "m2,image_point,default,cam,block.b,190,97,0.5,3.0\n"
        "m3,image_point,default,cam,block.c,190,142,2.0,2.0\n",
        encoding="utf-8",
    )
    engine = Engine(model, [given], [("cam", "default", photo)], out)
    assert [(c.sigma, c.sigma_v) for c in engine.session.clicks] == [(0.5, 3.0), (0.5, 3.0), (2.0, None)]
    saved = json.loads((out / SESSION_FILE).read_text())["clicks"]
    assert saved[0]["sigma"] == 0.5 and saved[0]["sigma_v"] == 3.0 and "sigma_v" not in saved[2]
    assert [list(m.sigma) for m in engine.measurements()] == [[0.5, 3.0], [0.5, 3.0], [2.0, 2.0]]  # the solve's
    # The page sends the clicks back as it got them: the schema takes both σ.
    srv = StudioServer(engine).start()
    try:
        c = _client(srv)
        clicks = c.get(_base(srv) + "/api/state").json()["session"]["clicks"]
        body = {"clicks": clicks, "estimate": ["block.x"], "values": {}}
        assert c.post(_base(srv) + "/api/session", json=body, headers={"Origin": _base(srv), **POST}).status_code == 200
    finally:
        srv.stop()
    assert engine.session.clicks[0].sigma_v == 3.0
    restored = Engine(model, [given], [("cam", "default", photo)], out)
    assert restored.session.clicks[1].sigma_v == 3.0
    assert restored.require_model().warm.wait(timeout=120)  # its compiles done before the process ends
    engine.save("csv")
    written = read_measurements(out / "measurements.csv", load_model(model))
    assert [list(m.sigma) for m in written] == [[0.5, 3.0], [0.5, 3.0], [2.0, 2.0]]
    # A correlated covariance cannot be a click: refused at start, not silently made diagonal.
    correlated = tmp_path / "cov.json"
    correlated.write_text(json.dumps({"measurements": [{"id": "m1", "kind": "image_point", "camera": "cam",
                          "point": "block.a", "u": 130, "v": 97, "cov": [[1, 0.5], [0.5, 1]]}]}))  # fmt: skip
    with pytest.raises(MbcalError, match="image point 'm1' has a covariance with correlation"):
        Engine(model, [correlated], [("cam", "default", photo)], tmp_path / "out2")


@pytest.mark.slow
def test_the_page_shows_both_sigmas_and_an_edit_sets_one_for_both(browser, small, tmp_path):
    model, photo, out = small
    given = tmp_path / "aniso.csv"
    given.write_text(
        "id,kind,camera,point,u,v,sigma_u,sigma_v\nm1,image_point,cam,block.a,130,97,0.5,3.0\n", encoding="utf-8"
    )
    srv = StudioServer(Engine(model, [given], [("cam", "default", photo)], out)).start()
    try:
        page = open_page(browser, srv.url)
        assert page.input_value("input[data-sigma='m1']") == "0.5"
        assert page.inner_text("span[data-sigma-v='m1']").strip() == "/ 3"
        page.fill("input[data-sigma='m1']", "0.8")
        page.press("input[data-sigma='m1']", "Enter")
        saved = _session_when(out, lambda s: s["clicks"][0]["sigma"] == 0.8)["clicks"][0]
        assert "sigma_v" not in saved
        assert page.locator("span[data-sigma-v='m1']").count() == 0
        page.close()
    finally:
        srv.stop()


def test_a_session_that_cannot_be_written_changes_nothing_and_says_so(small, monkeypatch):
    import mbcal.studio.engine as studio_engine

    model, photo, out = small
    engine = Engine(model, [], [("cam", "default", photo)], out)
    click = {"id": "c1", "camera": "cam", "config": "default", "point": "block.a", "u": 10.0, "v": 20.0, "sigma": 1.0}

    def full(*_args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(studio_engine, "save_session", full)
    with pytest.raises(MbcalError, match="cannot save the session to .*No space left on device"):
        engine.set_session([click], ["block.*"], {}, [])
    assert engine.session.clicks == []  # as before the refused edit: the page still has it to send again


@pytest.mark.slow
def test_the_page_says_not_saved_until_a_session_save_succeeds(browser, small):
    import shutil

    model, photo, out = small
    srv = StudioServer(Engine(model, [], [("cam", "default", photo)], out)).start()
    try:
        page = open_page(browser, srv.url)
        page.wait_for_selector("svg[data-photo='p0'] .wire path")
        shutil.rmtree(out)  # the folder is gone: the session cannot be written
        click_point(page, "p0", "block.a", 110.25, 80.5)
        page.wait_for_selector("body[data-unsaved='1']")
        assert page.inner_text("#status").startswith("NOT SAVED")
        out.mkdir()
        click_point(page, "p0", "block.b", 210.0, 81.0)
        page.wait_for_function("() => document.body.dataset.unsaved === ''")
        assert not page.inner_text("#status").startswith("NOT SAVED")
        assert len(_session_when(out, lambda s: len(s["clicks"]) == 2)["clicks"]) == 2  # both on disk now
        page.close()
    finally:
        srv.stop()


def test_the_wireframe_edge_cache_is_bounded(small, monkeypatch):
    import mbcal.studio.engine as studio_engine

    model, photo, out = small
    monkeypatch.setattr(studio_engine, "MAX_EDGE_SETS", 5)
    engine = Engine(model, [], [("cam", "default", photo)], out)
    loaded = engine.require_model()
    for k in range(12):
        edges = engine._edges(loaded, 0, np.array([0.4 + 0.01 * k, 0.3, 0.2]))
        assert edges is not None
    assert len(loaded.edges) == 5


def test_bodies_the_framework_refuses_get_the_pages_error_format(server):
    base = _base(server)
    headers = {TOKEN_HEADER: server.token, "Origin": base, "Content-Type": "application/json"}
    for body in (b"[" * 5000 + b"]" * 5000, b"\xff\xfe{"):
        r = httpx.post(base + "/api/session", content=body, headers=headers)
        assert r.status_code == 400 and r.json()["error"]["message"].startswith("invalid request")
        assert r.headers["x-frame-options"] == "DENY"
