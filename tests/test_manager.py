"""The environment model manager: tracking a rotating lever, naming a structural misfit, and
surviving kill -9 in the middle of an update."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import mbcal
from mbcal.range.fit import fit_scans
from mbcal.range.manager import ModelManager
from mbcal.range.readers import write_depth_png
from mbcal.range.scans import Scan, depth_camera, depth_to_points
from mbcal.range.simulate import add_depth_noise, render_depth

from conftest import MODELS

ROOM = MODELS / "teleexistence.mdl"


def _model_file(
    tmp_path: Path,
    width: int = 106,
    height: int = 60,
    eye: str = "(0.1 m, 0.05 m, 1.45 m)",
    target: str = "(0, 0.8 m, 1.1 m)",
) -> Path:
    path = tmp_path / "room.mdl"
    path.write_text(
        f'include "{ROOM}"\n'
        f"frame tripod at look_at(eye = {eye}, target = {target}) {{\n"
        f"  range depth_cam(width = {width}, height = {height}, f = {width / 2}, scale = 1 mm, "
        "min = 30 cm, max = 3 m)\n"
        "}\n"
    )
    return path


def _scan(model, truth, seed, sigma=1.5e-3, shapes=None) -> Scan:
    info = depth_camera(model)
    depth = add_depth_noise(render_depth(model, truth, shapes=shapes), sigma, 0.0, seed=seed)
    pts, pixels, _ = depth_to_points(depth, info)
    # With its pixels, as load_scan gives it: down-sampled on the pixel grid, not by noisy 3-D voxels.
    assert info.intrinsics is not None
    name = model.frames[info.frame].name
    return Scan(pts, name, sigma=sigma, source=f"seed {seed}", pixels=pixels, focal=min(info.intrinsics[:2]))


ROOM_TRUTH = {"room.x": 0.01, "room.y": -0.006, "room.z": 0.004, "room.yaw": np.radians(0.8)}


@pytest.mark.slow
def test_lever_rotating_over_20_batches_is_tracked_within_3_sigma(tmp_path):
    # Beside the valve, looking across the lever's plane of rotation: its turning tilts its faces
    # in depth, which point-to-surface distances see (face-on, only its silhouette would move).
    path = _model_file(tmp_path, 160, 90, eye="(-0.5 m, 0.45 m, 1.25 m)", target="(-0.12 m, 0.72 m, 1.1 m)")
    manager = ModelManager(
        path, tmp_path / "out", ["room.*", "lever.angle"], process_noise={"lever.angle": np.radians(3.0)}
    )
    model = manager.model
    sigmas = []
    for k in range(20):
        angle = np.radians(20.0 + 1.5 * k)  # the operator pulls the lever down slowly
        truth = {**ROOM_TRUTH, "lever.angle": angle}
        # 0.6 mm: a structured-light camera at 0.4 m.  (With 1.5 mm noise on this 2.5 cm wide lever
        # the unsigned point-to-surface distance near its edges biases the angle by about 3σ:
        # docs/range.md, limitations.)
        u = manager.update([_scan(model, truth, seed=k, sigma=0.6e-3)])
        assert u.accepted, u
        for name, value in u.values.items():  # every estimated parameter, at every step
            z = abs(value - truth.get(name, 0.0)) / u.std[name]  # room.roll and room.pitch: truly 0
            assert z < 3.0, f"batch {k}: {name} {z:.2f}σ off"
        sigmas.append(u.std["room.x"])
        assert not any(d.startswith("lever.angle") for d in u.drift)  # expected motion: no drift flag
    assert sigmas[-1] < 0.6 * sigmas[0]  # the room's pose tightens as batches accumulate
    bumped = {**ROOM_TRUTH, "room.x": ROOM_TRUTH["room.x"] + 0.02, "lever.angle": np.radians(48.5)}
    u = manager.update([_scan(model, bumped, seed=99, sigma=0.6e-3)])
    assert any(d.startswith("room.x moved") for d in u.drift), u.drift  # someone bumped the room
    history = [json.loads(line) for line in (tmp_path / "out" / "history.jsonl").read_text().splitlines()]
    assert [h["seq"] for h in history] == list(range(1, 22))
    calibrated = mbcal.load_model(tmp_path / "out" / "room.calibrated.mdl")
    assert calibrated.param("lever.angle").nominal == pytest.approx(history[-1]["values"]["lever.angle"], abs=1e-9)


@pytest.mark.slow
def test_box_replaced_by_cylinder_is_named_as_structural_misfit(tmp_path):
    import trimesh

    model = mbcal.load_model(_model_file(tmp_path, 160, 90))
    box = model.shape_index("room.box.housing")
    cylinder = trimesh.creation.cylinder(radius=0.05, height=0.12, sections=128)
    fit = fit_scans(model, [_scan(model, ROOM_TRUTH, seed=3, shapes={box: cylinder})], ["room.*"])
    assert [m.object for m in fit.structural] == ["room.box"], fit.text()
    text = fit.text()
    assert "room.box: " in text and "% of its points are farther than 3σ" in text
    assert "from the modelled box; its shape no longer fits" in text
    assert not fit.ok  # a wrong model never looks right
    clean = fit_scans(model, [_scan(model, ROOM_TRUTH, seed=3)], ["room.*"])
    assert clean.structural == [] and clean.ok


def _journal(out: Path) -> list[dict]:
    path = out / "history.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.endswith("}")]


@pytest.mark.slow
def test_kill_9_during_an_update_loses_no_accepted_update(tmp_path):
    path = _model_file(tmp_path, 64, 36)
    model = mbcal.load_model(path)
    scans = tmp_path / "scans"
    scans.mkdir()
    info = depth_camera(model)
    count = 10  # updates take ~0.1 s warm: enough of them that the kill lands inside the run
    for k in range(count):
        depth = add_depth_noise(render_depth(model, {**ROOM_TRUTH, "room.x": 0.01 + 0.001 * k}), 1.5e-3, seed=k)
        write_depth_png(scans / f"scan_{k:02d}.png", depth, info.depth_scale)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "mbcal", "watch", str(path), "--scans", str(scans), "--out", str(out)]
    cmd += ["--estimate", "room.*", "--once"]
    env = {**os.environ, "MBCAL_CACHE_DIR": os.environ.get("MBCAL_CACHE_DIR", str(tmp_path / "cache"))}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 300
    while len(_journal(out)) < 1 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = _journal(out)
    assert 1 <= len(before) < count, proc.stderr.read().decode() if proc.stderr else ""
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "resumed" in run.stdout
    after = _journal(out)
    assert after[: len(before)] == before  # nothing accepted was lost or rewritten
    assert [h["seq"] for h in after] == list(range(1, count + 1))
    assert sorted(Path(f).name for h in after for f in h["files"]) == [f"scan_{k:02d}.png" for k in range(count)]
    assert not list(out.glob(".*.part"))
    state = json.loads((out / "state.json").read_text())
    assert state["seq"] == count
    calibrated = mbcal.load_model(out / "room.calibrated.mdl")
    assert calibrated.param("room.x").nominal == pytest.approx(after[-1]["values"]["room.x"], abs=1e-9)


def test_an_unreadable_scan_is_journalled_and_the_watch_goes_on(tmp_path):
    """A scan file that cannot be read is a rejected update with the reason in the journal; the
    next file is still taken, a restart does not stop at the bad one again, and once the bad file
    is replaced it is read."""
    model_path = _model_file(tmp_path)
    model = mbcal.load_model(model_path)
    scans, out = tmp_path / "in", tmp_path / "out"
    scans.mkdir()
    depth = add_depth_noise(render_depth(model, ROOM_TRUTH), 1.5e-3, 0.0, seed=1)
    (scans / "scan_0001.png").write_bytes(b"partial")
    write_depth_png(scans / "scan_0002.png", depth)
    manager = ModelManager(model_path, out, ["room.x", "room.y", "room.z", "room.yaw"])
    seen = []
    assert manager.watch(scans, once=True, report=seen.append) == 2
    bad, good = seen
    assert not bad.accepted and "scan_0001.png" in bad.error and "cannot read" in bad.error
    assert np.isnan(bad.chi2) and np.isnan(bad.reduced_chi2)  # nothing was fitted: not a perfect fit of 0
    assert good.accepted and not good.error and abs(good.values["room.x"] - 0.01) < 3 * good.std["room.x"]
    journal = _journal(out)
    assert [bool(e["error"]) for e in journal] == [True, False]
    assert journal[0]["chi2"] is None and journal[0]["reduced_chi2"] is None
    # A restart skips both: the good one was taken, the bad one has not changed.
    again = ModelManager(model_path, out, ["room.x", "room.y", "room.z", "room.yaw"])
    assert again.watch(scans, once=True) == 0
    # Replaced by a readable scan, the file is read (and the state stays the last accepted one's).
    write_depth_png(scans / "scan_0001.png", depth)
    seen.clear()
    assert again.watch(scans, once=True, report=seen.append) == 1
    assert seen[0].accepted and not seen[0].error and seen[0].files == [str((scans / "scan_0001.png").resolve())]


@pytest.mark.slow
def test_watch_json_prints_one_strict_json_object_per_update(tmp_path, capsys):
    """`mbcal watch --json`: each update, the rejected one too, as one line of strict JSON with the
    journal's fields (a pipeline reads stdout; the text lines and 'resumed' stay off it)."""
    from mbcal.cli import main

    model_path = _model_file(tmp_path)
    model = mbcal.load_model(model_path)
    scans, out = tmp_path / "in", tmp_path / "out"
    scans.mkdir()
    (scans / "scan_0001.png").write_bytes(b"partial")
    write_depth_png(scans / "scan_0002.png", add_depth_noise(render_depth(model, ROOM_TRUTH), 1.5e-3, 0.0, seed=1))
    argv = ["watch", str(model_path), "--scans", str(scans), "--out", str(out), "--estimate", "room.*", "--once"]

    def strict(text):
        def refuse(token):
            raise AssertionError(f"{token} is not JSON")

        return json.loads(text, parse_constant=refuse)

    assert main([*argv, "--json"]) == 1  # an update of this run was rejected
    lines = capsys.readouterr().out.splitlines()
    bad, good = (strict(line) for line in lines)
    assert (bad["seq"], good["seq"]) == (1, 2)
    assert not bad["accepted"] and "cannot read" in bad["error"]
    assert good["accepted"] and not good["error"]
    assert good == strict((out / "history.jsonl").read_text().splitlines()[1])  # the journal's record
    assert abs(good["values"]["room.x"] - ROOM_TRUTH["room.x"]) < 3 * good["std"]["room.x"]
    # a restart with nothing new prints no line on stdout (and rejects nothing: exit 0); 'resumed' goes to stderr
    assert main([*argv, "--json"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and "resumed: 2 updates" in captured.err
    assert "update 1 (REJECTED" not in captured.out
    # non-finite numbers become null
    from mbcal.outputs import finite_or_null

    assert finite_or_null({"a": [float("inf"), 1.0], "b": float("nan"), "c": "x"}) == {
        "a": [None, 1.0],
        "b": None,
        "c": "x",
    }


def test_process_noise_must_name_an_estimated_unknown(tmp_path):
    model_path = _model_file(tmp_path)
    with pytest.raises(mbcal.MbcalError, match="no estimated unknown matches it"):
        ModelManager(model_path, tmp_path / "out", ["room.*"], process_noise={"lever.angle": 0.1})
    with pytest.raises(mbcal.MbcalError, match="finite σ ≥ 0"):
        ModelManager(model_path, tmp_path / "out", ["room.*"], process_noise={"room.yaw": -1.0})


def test_an_update_with_an_undetermined_unknown_is_strict_json_and_reads_back_infinite():
    """The journal is JSON lines: an infinite σ (an unknown no scan determines) and the χ² of an
    unreadable scan are null in it (json.dumps wrote Infinity and NaN, which other readers refuse),
    and read back as ∞ and NaN."""
    from mbcal.range.manager import Update

    u = Update(1, 0.0, {"a": 1.0, "b": 2.0}, {"a": 0.1, "b": float("inf")}, float("nan"), float("nan"), 0, 0, False)
    text = json.dumps(u.to_json(), allow_nan=False)
    back = Update.from_json(json.loads(text))
    assert back.std == {"a": 0.1, "b": float("inf")} and np.isnan(back.chi2) and np.isnan(back.reduced_chi2)
    assert back.values == u.values and not back.accepted


def test_a_link_to_nothing_is_a_rejected_update_and_a_folder_is_no_scan(tmp_path):
    """A dangling symbolic link stopped the watch ('No such file or directory', exit 2); a folder
    named like a scan was reported as a missing file."""
    from mbcal.range.manager import ModelManager

    scans = tmp_path / "in"
    scans.mkdir()
    (scans / "a.ply").symlink_to(tmp_path / "nowhere.ply")
    (scans / "d.ply").mkdir()
    manager = ModelManager(MODELS / "room_depth.mdl", tmp_path / "out", ["room.*"])
    seen = []
    assert manager.watch(scans, once=True, report=seen.append) == 1
    assert not seen[0].accepted and "a link to a file that does not exist" in seen[0].error
    assert manager.watch(scans, once=True) == 0  # not taken again until it changes


def test_an_update_the_scan_fit_would_not_trust_is_rejected_and_changes_nothing(tmp_path):
    """The reviewer's cases: a flat wall after the room (it fits some plane of the model at a pose
    25° off, which only the previous state had pinned) and a scan noisier than its σ were accepted:
    the state and the calibrated model replaced, and `watch --once` exited 0."""
    path = _model_file(tmp_path)
    manager = ModelManager(path, tmp_path / "out", ["room.*"])
    model = manager.model
    first = manager.update([_scan(model, ROOM_TRUTH, seed=1)])
    assert first.accepted and not first.doubts
    state = (tmp_path / "out" / "state.json").read_bytes()
    calibrated = (tmp_path / "out" / "room.calibrated.mdl").read_bytes()
    info = depth_camera(model)
    wall = np.full((info.height, info.width), 1.0)  # every pixel 1 m away: a flat wall
    pts, pixels, _ = depth_to_points(wall, info)
    name = model.frames[info.frame].name
    flat = Scan(pts, name, sigma=1.5e-3, source="wall", pixels=pixels, focal=min(info.intrinsics[:2]))
    u = manager.update([flat])
    assert not u.accepted and any("contradicts the previous state" in d for d in u.doubts), u.doubts
    noisy = manager.update([dataclasses.replace(_scan(model, ROOM_TRUTH, seed=2, sigma=1.5e-3), sigma=0.4e-3)])
    assert not noisy.accepted and any("scatter more than σ" in d for d in noisy.doubts), noisy.doubts
    # neither replaced what the accepted update wrote
    assert (tmp_path / "out" / "state.json").read_bytes() == state
    assert (tmp_path / "out" / "room.calibrated.mdl").read_bytes() == calibrated
    # the scans on their own: the same verdicts from mbcal fit's rule
    assert not fit_scans(model, [flat], ["room.*"]).ok


def test_watch_once_waits_for_a_scan_still_being_copied(tmp_path, monkeypatch):
    """'mbcal watch --once' took every file at first sight: a PNG still being copied was a rejected
    update ("cannot read") in the journal and the exit status 1.  A file modified less than the
    settle time ago is now waited for (until its size rests), with --once too."""
    import threading

    path = _model_file(tmp_path)
    model = mbcal.load_model(path)
    scans = tmp_path / "scans"
    scans.mkdir()
    write_depth_png(tmp_path / "whole.png", add_depth_noise(render_depth(model, ROOM_TRUTH), 1.5e-3, 0.0, seed=1))
    data = (tmp_path / "whole.png").read_bytes()
    target = scans / "a.png"
    target.write_bytes(data[: len(data) // 2])  # the copy has begun

    def finish() -> None:
        time.sleep(0.25)
        with target.open("ab") as f:
            f.write(data[len(data) // 2 :])

    copier = threading.Thread(target=finish)
    copier.start()
    seen = []
    try:
        assert ModelManager(path, tmp_path / "out", ["room.*"]).watch(scans, once=True, report=seen.append) == 1
    finally:
        copier.join()
    assert not seen[0].error and seen[0].accepted
    # A file last modified long ago is taken at first sight: the watch does not wait at all.
    os.utime(target, ns=(time.time_ns() - 10**10,) * 2)

    def no_wait(seconds: float) -> None:
        raise AssertionError(f"waited {seconds} s for a file modified 10 s ago")

    monkeypatch.setattr("mbcal.range.manager.time.sleep", no_wait)
    assert ModelManager(path, tmp_path / "out2", ["room.*"]).watch(scans, once=True) == 1


def test_a_scan_file_that_changes_after_it_was_taken_is_taken_again(tmp_path):
    """A copy that paused half-way was taken (the size had settled) and never read again: the rest
    of the scan was lost without a word.  A taken file is now read again when its size or time
    changes; one that has not changed is not (nor after a restart)."""
    path = _model_file(tmp_path)
    model = mbcal.load_model(path)
    scans = tmp_path / "scans"
    scans.mkdir()
    depth = render_depth(model, ROOM_TRUTH)
    write_depth_png(scans / "a.png", add_depth_noise(depth, 1.5e-3, 0.0, seed=1))
    manager = ModelManager(path, tmp_path / "out", ["room.*"])
    assert manager.watch(scans, once=True) == 1
    assert manager.watch(scans, once=True) == 0  # unchanged: not again
    write_depth_png(scans / "a.png", add_depth_noise(depth, 1.5e-3, 0.0, seed=2))  # the file changed
    os.utime(scans / "a.png", ns=(time.time_ns(), time.time_ns() + 10**9))
    resumed = ModelManager(path, tmp_path / "out", ["room.*"])  # from the journal, as after a restart
    assert resumed.watch(scans, once=True) == 1
    assert [u.files for u in resumed.history] == [[str((scans / "a.png").resolve())]] * 2
    assert all(len(u.stamp) == 2 for u in resumed.history)
    assert ModelManager(path, tmp_path / "out", ["room.*"]).watch(scans, once=True) == 0
