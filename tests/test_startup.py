"""Process-level overhead of the command line (issue 16): the fast exit, one shared OpenGL context
for every rendered view, passes rendered only when used, and heavy libraries left unloaded where a
command does not need them.  Counts and identities are checked, never times."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import MODELS, ROOT


def python(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env={**os.environ, **env}, timeout=300
    )


EXIT = (
    "import atexit, sys\n"
    "atexit.register(lambda: print('teardown ran'))\n"
    "from mbcal.cli import exit_now\n"
    "{before}"
    "sys.stdout.write('x' * 200000)\n"  # buffered, not flushed yet
    "sys.stderr.write('said on stderr')\n"
    "exit_now(3)\n"
)


def test_the_fast_exit_flushes_everything_keeps_the_status_and_skips_the_teardown():
    proc = python(EXIT.format(before=""))
    assert proc.returncode == 3
    assert proc.stdout == "x" * 200000  # all of it, and no atexit handler ran
    assert proc.stderr == "said on stderr"


@pytest.mark.parametrize(
    "before, env",
    [
        ("", {"MBCAL_FAST_EXIT": "0"}),  # asked for the ordinary exit
        ("sys.settrace(lambda *a: None)\n", {}),  # a tracer (coverage) must be able to save its data
        ("import cProfile; cProfile.Profile().enable()\n", {}),  # so must a profiler
    ],
)
def test_python_exits_normally_when_asked_or_under_a_tracer_or_profiler(before, env):
    proc = python(EXIT.format(before=before), **env)
    assert proc.returncode == 3
    assert proc.stdout == "x" * 200000 + "teardown ran\n"


def test_the_mbcal_command_ends_with_its_status_and_its_whole_output():
    run = [sys.executable, "-m", "mbcal"]
    fast = subprocess.run([*run, "check", str(MODELS / "teleexistence.mdl")], capture_output=True, text=True, cwd=ROOT)
    slow = subprocess.run(
        [*run, "check", str(MODELS / "teleexistence.mdl")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "MBCAL_FAST_EXIT": "0"},
    )
    assert fast.returncode == slow.returncode == 0
    assert fast.stdout == slow.stdout and len(fast.stdout) > 200
    bad = subprocess.run([*run, "check", "no/such/model.mdl"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "no/such/model.mdl" in bad.stderr and "Traceback" not in bad.stderr


def test_drawing_an_overlay_with_its_legend_does_not_import_matplotlib():
    # The legend's font is matplotlib's DejaVu Sans, found by its file, not through font_manager
    # (importing matplotlib cost ~0.25 s of `calibrate-camera --overlay` and `solve --overlay`).
    code = (
        "import json, sys\n"
        "import numpy as np\n"
        "from mbcal.render.views import Layer, _font_file, draw_overlay\n"
        "image = np.full((60, 80, 3), 200, np.uint8)\n"
        "layers = [Layer('wireframe', [(np.array([[5.0, 5], [40, 30], [np.nan, 1], [70, 50], [75, 55]]),"
        " np.array([True, True, True, True, False]))], (255, 0, 0), 1.5, 'model'),"
        " Layer('labels', [((10.0, 20.0), 'p1')], (0, 0, 255))]\n"
        "out = np.asarray(draw_overlay(image, layers))\n"
        "print(json.dumps({'font': _font_file(), 'changed': int((out != 200).any(axis=2).sum()),"
        " 'loaded': sorted(m for m in sys.modules if m.split('.')[0] == 'matplotlib')}))\n"
    )
    proc = python(code)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["loaded"] == []
    assert out["changed"] > 100  # the line, the label and the legend were drawn
    from matplotlib import font_manager

    assert os.path.samefile(out["font"], font_manager.findfont("DejaVu Sans", fallback_to_default=True))


# ---- rendering: one context for every view ------------------------------------------------------------


SMALL = """
frame box_frame at (0, 2 m, 1 m) {
  shape crate = box(60 cm, 40 cm, 50 cm) at rot_z(20 deg)
}
frame eye at look_at(eye = (0, 0, 1.2 m), target = (0, 2 m, 1.0 m)) {
  camera cam(width = 160, height = 120, fx = 150, fy = 150, cx = 79.5, cy = 59.5)
}
"""


@pytest.fixture(scope="module")
def scenes():
    from mbcal.language import load_model, load_model_text
    from mbcal.modeling import modeler

    room = load_model(MODELS / "teleexistence.mdl")
    small = load_model_text(SMALL)
    return modeler(room, room.nominal), modeler(small, small.nominal)


def same_view(a, b) -> None:
    np.testing.assert_array_equal(a.color, b.color)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.shape_index, b.shape_index)


@pytest.mark.render
def test_views_in_a_block_share_one_context_and_another_scene_in_between_changes_nothing(scenes):
    from mbcal.render import views

    room, small = scenes
    alone = views.render_view(room, "eyes.left")  # outside a block: its own context, closed after it
    assert views._RENDERER._renderer is None
    with views.shared_context():
        first = views.render_view(room, "eyes.left")
        context = views._RENDERER._renderer
        assert context is not None
        with views.shared_context():  # blocks nest
            other = views.render_view(small, "cam")  # another scene, another image size, the same context
        assert views._RENDERER._renderer is context
        assert other.color.shape == (120, 160, 3) and (other.shape_index == 0).any()
        again = views.render_view(room, "eyes.left")
        assert views._RENDERER._renderer is context
    assert views._RENDERER._renderer is None  # closed with the outermost block
    same_view(first, alone)
    same_view(again, first)  # nothing of the small scene was left in the context


@pytest.mark.render
def test_a_depth_simulation_between_two_views_outside_a_block_breaks_nothing():
    # Closing any pyrender context terminates the EGL display all of them share: a context kept
    # beyond a block would fail after range.simulate's renderer closed (this once happened).
    from mbcal.language import load_model
    from mbcal.modeling import modeler
    from mbcal.range.simulate import render_depth
    from mbcal.render.views import render_view

    from conftest import ROOM_TRUTH

    model = load_model(MODELS / "room_depth.mdl")
    scene = modeler(model, model.nominal)
    camera = model.cameras[0].name
    first = render_view(scene, camera)
    depth = render_depth(model, ROOM_TRUTH)
    same_view(render_view(scene, camera), first)
    np.testing.assert_array_equal(render_depth(model, ROOM_TRUTH), depth)


@pytest.mark.render
def test_a_pass_left_out_is_empty_and_the_other_is_unchanged(scenes):
    from mbcal.render.views import render_view

    room, _ = scenes
    both = render_view(room, "eyes.right")
    colour = render_view(room, "eyes.right", depth=False)
    depth = render_view(room, "eyes.right", color=False)
    np.testing.assert_array_equal(colour.color, both.color)
    assert colour.depth.size == 0 and colour.shape_index.size == 0
    np.testing.assert_array_equal(depth.depth, both.depth)
    np.testing.assert_array_equal(depth.shape_index, both.shape_index)
    assert depth.color.size == 0
    assert (both.shape_index >= 0).mean() > 0.5 and both.depth.max() > 0


@pytest.mark.slow
@pytest.mark.parametrize("overlay", [False, True])
def test_calibrate_camera_loads_no_plotting_rendering_or_opencv(tmp_path, overlay):
    # The command's own path: JAX, SciPy's special functions, the model language; no matplotlib,
    # pyrender, trimesh or OpenCV (they load only for detect, render, solve's overlays, demo), and
    # Pillow only to draw the reprojected corners over an image.
    model, corners = str(MODELS / "camera_calibration.mdl"), str(tmp_path / "corners.json")
    argv = ["calibrate-camera", model, corners, "--quiet", "--json", str(tmp_path / "out.json")]
    if overlay:
        from PIL import Image

        Image.fromarray(np.full((480, 640, 3), 128, np.uint8)).save(tmp_path / "photo.png")
        argv += ["--overlay", str(tmp_path / "overlays"), "--image", f"view01={tmp_path / 'photo.png'}"]
    code = (
        "import json, sys\n"
        "import mbcal\n"
        "from mbcal.measurements.io import write_measurements\n"
        "from mbcal.workflows.cameras import simulate_views\n"
        f"model = mbcal.load_model({model!r})\n"
        "truth = {'cam.fx': 812.0, 'cam.fy': 806.5, 'cam.cx': 327.0, 'cam.cy': 236.0}\n"
        "data = simulate_views(model, 3, truth, seed=1, distance=(0.45, 0.7))[0]\n"
        f"write_measurements(data, {corners!r})\n"
        "from mbcal.cli import main\n"
        f"code = main({argv!r})\n"
        "print()\n"
        "print(json.dumps({'code': code, 'loaded': sorted(m for m in sys.modules if '.' not in m)}))\n"
    )
    proc = python(code, MBCAL_CACHE_DIR=str(tmp_path / "cache"))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["code"] in (0, 1)
    heavy = ("matplotlib", "pyrender", "trimesh", "cv2", "OpenGL", "networkx") + (() if overlay else ("PIL",))
    assert not [m for m in heavy if m in out["loaded"]], out["loaded"]
    assert json.loads((tmp_path / "out.json").read_text())  # it did calibrate
    if overlay:
        assert "PIL" in out["loaded"] and len(list((tmp_path / "overlays").glob("*.png"))) == 1


COLLECTOR = """
import gc, json
from mbcal._collector import end_start_up, gc_paused, pause_start_up
seen = {{}}
{body}
print(json.dumps(seen))
"""


def collector(body: str) -> dict:
    proc = python(COLLECTOR.format(body=body))
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_collector_is_held_while_a_program_compiles_and_given_back_as_it_was():
    seen = collector(
        "from mbcal._jax import jit, jnp\n"
        "def f(x):\n"
        "    seen['inside'] = gc.isenabled()\n"  # runs while the program is traced
        "    return x + 1\n"
        "jit(f)(jnp.ones(3))\n"
        "seen['after'] = gc.isenabled()\n"
        "with gc_paused():\n"
        "    with gc_paused():\n"
        "        seen['nested'] = gc.isenabled()\n"
        "    seen['outer'] = gc.isenabled()\n"
        "seen['left'] = gc.isenabled()\n"
        "gc.disable()\n"  # a caller's own choice stays
        "with gc_paused():\n"
        "    pass\n"
        "seen['callers'] = gc.isenabled()\n"
        "seen['frozen'] = gc.get_freeze_count()\n"
    )
    assert seen == {
        "inside": False,
        "after": True,
        "nested": False,
        "outer": False,
        "left": True,
        "callers": False,
        "frozen": 0,
    }  # a library caller's process is never frozen


def test_no_pause_under_disable_jit_and_a_forked_child_does_not_inherit_a_pause():
    seen = collector(
        "import os\n"
        "from mbcal._jax import jax, jit, jnp\n"
        "def f(x):\n"
        "    seen['op by op'] = gc.isenabled()\n"
        "    return x + 1\n"
        "with jax.disable_jit():\n"  # a whole solve would run in Python: the collector stays on
        "    jit(f)(jnp.ones(3))\n"
        "with gc_paused():\n"  # as if another thread held it while this one forks
        "    pid = os.fork()\n"
        "    if pid == 0:\n"
        "        os._exit(0 if gc.isenabled() else 1)\n"
        "    seen['child'] = os.waitpid(pid, 0)[1] == 0\n"
        "seen['after'] = gc.isenabled()\n"
    )
    assert seen == {"op by op": True, "child": True, "after": True}


def test_the_command_lines_start_up_pause_ends_at_its_first_program_with_what_start_up_built_frozen():
    seen = collector(
        "pause_start_up()\n"
        "seen['paused'] = gc.isenabled()\n"
        "from mbcal._jax import jit, jnp\n"  # start-up: JAX's import, without collections
        "seen['before'] = gc.get_freeze_count()\n"
        "def f(x):\n"
        "    seen['tracing'] = gc.isenabled()\n"
        "    return x * 2\n"
        "jit(f)(jnp.ones(3))\n"
        "seen['after'] = gc.isenabled()\n"
        "seen['frozen'] = gc.get_freeze_count()\n"
    )
    assert seen["paused"] is False and seen["before"] == 0 and seen["tracing"] is False
    assert seen["after"] is True and seen["frozen"] > 50_000  # JAX's modules: no later collection walks them
    # A command that waits before any program (the studio's server) ends the pause itself.
    seen = collector(
        "pause_start_up()\nend_start_up()\nseen['on'] = gc.isenabled()\nseen['frozen'] = gc.get_freeze_count()\n"
    )
    assert seen["on"] is True and seen["frozen"] > 0


def test_the_mbcal_command_starts_without_collections():
    proc = python(
        "import gc, mbcal.cli\n"
        "mbcal.cli.entry = lambda: print('collector on' if gc.isenabled() else 'collector paused')\n"
        "from mbcal.__main__ import run\n"
        "print('before', gc.isenabled())\n"
        "run()\n"
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split("\n")[:2] == ["before True", "collector paused"]
