"""The model's own known values are constants of a problem's programs (issue 16): the programs
must compute with them as they computed with inputs, and must never serve other values."""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import mbcal
import mbcal.language.load as load_module
from mbcal.problem import Problem

from conftest import MODELS, ROOT

CAMERA = "camera eye(width = 640, height = 480, f = 500) at look_at(eye = (0, -3 m, 1 m), target = (0, 0, 1 m))\n"


def _one_point(body: str, model_text: str | None = None):
    model = mbcal.load_model_text(model_text or f"param a = 0 m in [-1 m, 1 m]\n{body}\n{CAMERA}")
    plan = mbcal.measurements_from_records(
        [{"id": "p", "kind": "image_point", "camera": "eye", "point": "p", "sigma": 1.0}], model
    )
    return model, plan


@pytest.mark.parametrize(
    "value, expression, u",
    [
        ("0", "min(1 m / k, 2 m)", 652.8333333333334),  # 1 / 0 = inf, then the 2 m
        ("0", "min(k^-1 * 1 m, 2 m)", 652.8333333333334),
        ("-4", "max(k^0.5, 0) * 1 m", 319.5),  # (-4)^0.5 = NaN, and max(NaN, 0) = 0 as when traced
    ],
)
def test_a_constant_computes_as_the_traced_value_did(value, expression, u):
    """A known value of the model became a Python float while tracing: 1 / 0, 0^-1 and a negative
    number to a fractional power raised ZeroDivisionError or gave a complex number (tracebacks),
    where the traced program gives inf and NaN."""
    model, plan = _one_point(f"param k = {value}\nframe f at (a, 0, 0) {{\n  point p = ({expression}, 0, 1 m)\n}}")
    folded = Problem(model, plan, ["a"]).predict()
    given = Problem(model, plan, ["a"], known={"k": float(value)}).predict()  # an input, as before
    assert np.allclose(folded, [u, 239.5]) and np.allclose(given, folded)


def test_a_known_array_that_changes_a_constant_gives_nan_not_the_old_value():
    """residual_function(x, y, known) ignored the constant columns of a caller's known (the lever
    length stayed 25 cm when known said 40 cm); the local residual read them: the two disagreed."""
    model = mbcal.load_model(MODELS / "teleexistence.mdl")
    plan = mbcal.read_measurements(MODELS.parent / "measurements" / "room_plan.csv", model)
    data = mbcal.simulate(model, plan, {"room.x": 0.01}, noise=0.0)
    problem = Problem(model, data, ["room.*"])
    x, known = problem.params.x0, problem.params.known.copy()
    d = np.zeros_like(x)
    for f in (
        lambda k: problem.residual_function(x, problem.y, k),
        lambda k: problem.local.residual(x, d, problem.y, k),
    ):
        assert np.all(np.isfinite(f(known)))
        changed = known.copy()
        changed[:, model.param_index("lever.length")] = 0.40
        assert np.all(np.isnan(f(changed)))
    assert np.allclose(problem.residual_function(x, problem.y, known), problem.local.residual(x, d, problem.y, known))


def test_point_files_and_plugin_code_are_part_of_the_fingerprint(tmp_path, monkeypatch):
    """A point file's points are constants of the programs, and a plugin measurement model's code
    is traced into them: an edited file or plugin reused the program of the old one from the
    disk cache (silently the old points / the old prediction)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "c.txt").write_text("0 0\n")
    text = (
        "param a = 0 m in [-1 m, 1 m]\n"
        'frame f at (a, 0, 1 m) {\n  target t = points("c.txt", scale = 1 m, columns = 2)\n}\n' + CAMERA
    )
    (tmp_path / "m.mdl").write_text(text)

    def fingerprint():
        model = mbcal.load_model(tmp_path / "m.mdl")
        plan = mbcal.measurements_from_records(
            [{"id": "p", "kind": "image_point", "camera": "eye", "point": "f.t.p0", "sigma": 1.0}], model
        )
        return Problem(model, plan, ["a"]).fingerprint()

    first = fingerprint()
    (tmp_path / "c.txt").write_text("0.5 0\n")
    second = fingerprint()
    assert second != first
    # a file saved after the model was read: the problem is keyed by what the model holds (the
    # edited file's key held the program of the old points)
    model = mbcal.load_model(tmp_path / "m.mdl")
    plan = mbcal.measurements_from_records(
        [{"id": "p", "kind": "image_point", "camera": "eye", "point": "f.t.p0", "sigma": 1.0}], model
    )
    (tmp_path / "c.txt").write_text("0.75 0\n")
    (tmp_path / "m.mdl").write_text(text.replace("[-1 m, 1 m]", "[-2 m, 2 m]"))
    assert Problem(model, plan, ["a"]).fingerprint() == second
    assert fingerprint() not in (first, second)

    # a file saved while the model is being read: keyed by what the model holds, not by the new file
    def check_then_save(*a, **k):
        model = original_check(*a, **k)
        (tmp_path / "c.txt").write_text("0.25 0\n")
        return model

    (tmp_path / "c.txt").write_text("0.5 0\n")
    (tmp_path / "m.mdl").write_text(text)
    original_check = load_module.check
    monkeypatch.setattr(load_module, "check", check_then_save)
    model = mbcal.load_model(tmp_path / "m.mdl")
    monkeypatch.setattr(load_module, "check", original_check)
    assert float(model.points[0].position.value[0]) == 0.5
    plan = mbcal.measurements_from_records(
        [{"id": "p", "kind": "image_point", "camera": "eye", "point": "f.t.p0", "sigma": 1.0}], model
    )
    assert Problem(model, plan, ["a"]).fingerprint() == second != fingerprint()

    source = tmp_path / "zplugin.py"
    source.write_text(
        "from mbcal.measurements import MeasurementModel, Role\n"
        "class PointZ(MeasurementModel):\n"
        "    kind = 'point_z_test'\n"
        "    roles = (Role('point', 'point'),)\n"
        "    values = ('value',)\n"
        "    value_dimension = 'length'\n"
        "    def predict(self, scenes, batch):\n"
        "        return 1.0 * scenes.points[batch.config, batch.refs['point']][:, 2:3]\n"
    )
    spec = importlib.util.spec_from_file_location("zplugin", source)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "zplugin", module)
    spec.loader.exec_module(module)
    kinds = importlib.import_module("mbcal.measurements.registry")  # the package exports a function of its name
    monkeypatch.setitem(kinds._EXTRA, "point_z_test", module.PointZ())  # register(), undone after
    model = mbcal.load_model(MODELS / "lever.mdl")
    plan = mbcal.measurements_from_records([{"id": "t", "kind": "point_z_test", "point": "lever.tip"}], model)
    before = Problem(model, plan, ["lever.angle"]).fingerprint()
    source.write_text(source.read_text().replace("1.0 *", "2.0 *"))
    # the file changed but the process still runs the old code: the key is the old code's
    assert before is not None and Problem(model, plan, ["lever.angle"]).fingerprint() == before
    spec.loader.exec_module(module := importlib.util.module_from_spec(spec))  # the new code, loaded
    monkeypatch.setitem(sys.modules, "zplugin", module)
    kinds.register(module.PointZ())
    assert Problem(model, plan, ["lever.angle"]).fingerprint() not in (None, before)
    memory = type(sys)("zmemory")  # code without a file to hash (a notebook's cell)
    exec(source.read_text().replace("PointZ", "PointM"), memory.__dict__)  # noqa: S102 — the test's own text
    monkeypatch.setitem(sys.modules, "zmemory", memory)
    memory.PointM.__module__ = "zmemory"
    kinds.register(memory.PointM())
    assert Problem(model, plan, ["lever.angle"]).fingerprint() is None  # then no disk cache


def test_suggested_measurements_are_predicted_with_the_callers_known_values():
    """The candidates' problem was built without the caller's known values (--set): a suggestion's
    Jacobian row was that of the model's lever length, not of the one given."""
    from mbcal import api

    model = mbcal.load_model(MODELS / "lever.mdl")

    def plan(point):
        return mbcal.measurements_from_records(
            [{"id": "m", "kind": "image_point", "camera": "eye", "point": point, "sigma": 1.0}], model
        )

    given = {"lever.length": 0.30}
    problem = Problem(model, plan("lever.hub"), ["lever.angle"], known=given)
    rows = api._candidate_rows(problem, problem.params.x0, api._measured_keys(plan("lever.hub")))
    (tip,) = [J for record, J in rows if record.get("point") == "lever.tip"]
    truth = Problem(model, plan("lever.tip"), ["lever.angle"], known=given)
    assert np.allclose(tip, truth.jacobian(truth.params.x0), rtol=1e-9)
    plain = Problem(model, plan("lever.tip"), ["lever.angle"])
    assert not np.allclose(tip, plain.jacobian(plain.params.x0), rtol=1e-3)


def test_a_gltf_buffer_is_part_of_the_fingerprint(tmp_path, monkeypatch):
    """A .gltf reads its vertices from buffer files beside it: an edited buffer kept the old key."""
    import trimesh

    monkeypatch.chdir(tmp_path)

    def write(size):
        for name, data in trimesh.exchange.gltf.export_gltf(trimesh.creation.box(extents=(size,) * 3)).items():
            (tmp_path / name).write_bytes(data)

    write(0.1)
    (tmp_path / "m.mdl").write_text(
        "param a = 0 m in [-1 m, 1 m]\n"
        'frame f at (a, 0, 1 m) {\n  point p = (0, 0, 0)\n  shape s = mesh("model.gltf")\n}\n' + CAMERA
    )

    def fingerprint():
        model = mbcal.load_model(tmp_path / "m.mdl")
        plan = mbcal.measurements_from_records(
            [{"id": "p", "kind": "image_point", "camera": "eye", "point": "f.p", "sigma": 1.0}], model
        )
        return model, Problem(model, plan, ["a"]).fingerprint()

    model, first = fingerprint()
    buffers = [f for f in model.data_files if f.endswith(".bin")]
    assert buffers, model.data_files
    gltf = (tmp_path / "model.gltf").read_bytes()
    write(0.5)
    (tmp_path / "model.gltf").write_bytes(gltf)  # the same .gltf, another buffer
    model, again = fingerprint()
    assert np.ptp(model.shapes[0].mesh.vertices, axis=0)[0] == pytest.approx(0.5) and again != first


SOURCE_EDIT = """
import json, os, pathlib, sys, warnings
import numpy as np
import mbcal
from mbcal import cache
root = pathlib.Path(sys.argv[1])
assert pathlib.Path(mbcal.__file__).parent == root  # the copy, not the checkout
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    key = cache.code_fingerprint()  # read before the edit, the programs' key is the old code's
    if sys.argv[2] == "edit":  # saved after the import and after the key: the next import runs it
        solver = root / "solver.py"
        solver.write_text(solver.read_text() + "\\n# saved while a process ran\\n")
    import mbcal.solver  # noqa: F401
    from mbcal._jax import jit, jnp

    def traced(x):
        if sys.argv[2] == "during":  # saved, and its module first imported, while the program traces
            text = root / "text.py"
            text.write_text(text.read_text() + "\\n# saved while a program traced\\n")
            import mbcal.text  # noqa: F401
        return jnp.sin(x) * 2.0

    program = cache.exported("a" * 64, jit(traced), np.zeros(3))
    assert np.allclose(np.asarray(program(np.full(3, 0.5))), 2.0 * np.sin(0.5))
    (root.parent / "m.mdl").write_text("param a = 1 m\\n")
    mbcal.load_model(root.parent / "m.mdl")
folder = pathlib.Path(os.environ["MBCAL_CACHE_DIR"])
print(json.dumps({"key": key, "exports": sorted(p.name for p in (folder / "exports").glob("*")),
                  "syntax": len(list((folder / "syntax").glob("*.json"))),
                  "warned": [str(w.message) for w in caught]}))
"""


def test_mbcal_source_saved_after_its_import_keeps_the_process_out_of_the_shared_cache(tmp_path):
    """The programs' key holds a hash of mbcal's source, read at first use: a file saved after the
    import (an edit beside a running notebook, an upgrade under a long process) and a module
    imported after that ran the new code under the old code's key, so the next process took the
    program of the code it does not run.  Such a process now neither reads nor writes the caches
    of programs and parsed files, and says so."""
    shutil.copytree(ROOT / "mbcal", tmp_path / "mbcal", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(ROOT / "grammar", tmp_path / "grammar")

    def run(mode, cache):
        env = {**os.environ, "PYTHONPATH": str(tmp_path), "MBCAL_CACHE_DIR": str(tmp_path / cache)}
        env.pop("MBCAL_CACHE", None)
        proc = subprocess.run(
            [sys.executable, "-c", SOURCE_EDIT, str(tmp_path / "mbcal"), mode],
            cwd=tmp_path,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout.strip().splitlines()[-1])

    plain = run("plain", "first")
    assert plain["warned"] == [] and plain["exports"] == ["a" * 64 + ".jaxexport"] and plain["syntax"] == 1
    edited = run("edit", "second")
    assert edited["key"] == plain["key"]  # the key was read before the save: only the check can tell
    assert edited["exports"] == [] and edited["syntax"] == 0
    assert sum("changed since mbcal was imported" in w for w in edited["warned"]) == 1
    after = run("plain", "second")  # the saved code, imported as it is: its own key, the cache again
    assert after["warned"] == [] and after["key"] != plain["key"] and after["exports"] and after["syntax"] == 1
    during = run("during", "third")  # looked at again right before the program is saved
    assert during["exports"] == [] and sum("changed since mbcal was imported" in w for w in during["warned"]) == 1
