"""Files mbcal writes: atomic, and with the permissions the user's umask gives (not 0600)."""

from __future__ import annotations

import os
import stat

import pytest

from mbcal.cli import main
from mbcal.outputs import atomic_write, atomic_writer, current_umask

from conftest import ROOT


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask():
    """Set the process's umask for one test and restore it afterwards."""
    old = os.umask(0o022)
    os.umask(old)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask, expected", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_new_files_get_the_permissions_of_the_umask(tmp_path, umask, mask, expected):
    umask(mask)
    assert current_umask() == mask
    atomic_write(tmp_path / "text.txt", "hello\n")
    with atomic_writer(tmp_path / "data.bin") as handle:
        handle.write(b"\x00\x01")
    # A command's output goes the same way.
    assert main(["convert", str(ROOT / "tests" / "data" / "arm7.urdf"), "-o", str(tmp_path / "arm7.mdl"), "-q"]) == 0
    for name in ("text.txt", "data.bin", "arm7.mdl"):
        assert mode(tmp_path / name) == expected, (name, oct(mode(tmp_path / name)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm7.mdl", "data.bin", "text.txt"]  # no .part left


def test_a_replaced_file_keeps_its_permissions(tmp_path, umask):
    umask(0o022)
    target = tmp_path / "report.json"
    target.write_text("old")
    os.chmod(target, 0o640)
    atomic_write(target, "new")
    assert target.read_text() == "new" and mode(target) == 0o640


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_writer(target, "w") as handle:
        handle.write("partial")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_a_temporary_file_that_cannot_be_made_is_said_of_the_file_asked_for(tmp_path, monkeypatch):
    """The error named '.r.json.wms7r9hz.part', a file the user never asked for."""
    import errno
    import tempfile

    from mbcal.errors import OutputError
    from mbcal.outputs import atomic_write

    def refuse(*args, **kwargs):
        raise OSError(errno.EACCES, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(OutputError, match=f"^cannot write {tmp_path / 'r.json'}: Permission denied"):
        atomic_write(tmp_path / "r.json", "{}")
    assert list(tmp_path.iterdir()) == []


def test_an_output_folder_the_system_refuses_is_found_before_the_work(tmp_path, monkeypatch):
    """The permission bits said yes (/proc to root) and the folder failed after the solve."""
    import errno
    import tempfile

    from mbcal.errors import OutputError
    from mbcal.outputs import check_output_folder

    def refuse(*args, **kwargs):
        raise OSError(errno.ENOENT, "No such file or directory")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    with pytest.raises(OutputError, match="--overlay: cannot write into .*: No such file or directory"):
        check_output_folder(tmp_path / "ov", "--overlay")
    monkeypatch.undo()
    assert check_output_folder(tmp_path / "ov", "--overlay") == tmp_path / "ov"
    assert list(tmp_path.iterdir()) == []  # the probe leaves nothing behind


def test_outputs_written_together_appear_together_or_not_at_all(tmp_path):
    from mbcal.outputs import all_or_nothing

    (tmp_path / "b.txt").write_text("old b")
    with pytest.raises(KeyboardInterrupt), all_or_nothing():
        atomic_write(tmp_path / "a.txt", "a")
        atomic_write(tmp_path / "b.txt", "new b")
        assert not (tmp_path / "a.txt").exists() and (tmp_path / "b.txt").read_text() == "old b"  # held back
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"] and (tmp_path / "b.txt").read_text() == "old b"
    with all_or_nothing():
        atomic_write(tmp_path / "a.txt", "a")
        atomic_write(tmp_path / "b.txt", "new b")
        atomic_write(tmp_path / "a.txt", "a again")  # the last write of a name wins, as without the block
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_text() == "a again" and (tmp_path / "b.txt").read_text() == "new b"
    atomic_write(tmp_path / "c.txt", "c")  # outside a block: at once
    assert (tmp_path / "c.txt").read_text() == "c"


def test_a_block_inside_another_fails_alone_and_else_appears_with_the_enclosing_ones_files(tmp_path):
    from mbcal.outputs import all_or_nothing, make_output_folder

    with all_or_nothing():
        atomic_write(tmp_path / "a.txt", "a")
        with pytest.raises(OSError), all_or_nothing():  # a part that fails: its files and folder go
            atomic_write(make_output_folder(tmp_path / "part") / "p.txt", "p")
            raise OSError("drawing failed")
        assert not (tmp_path / "part").exists()
        with all_or_nothing():  # a part that succeeds: held back until the enclosing block ends
            atomic_write(make_output_folder(tmp_path / "ok") / "q.txt", "q")
        assert not (tmp_path / "ok" / "q.txt").exists() and not (tmp_path / "a.txt").exists()
    assert (tmp_path / "a.txt").read_text() == "a" and (tmp_path / "ok" / "q.txt").read_text() == "q"
    with pytest.raises(KeyboardInterrupt), all_or_nothing():  # the enclosing block fails: the part goes too
        with all_or_nothing():
            atomic_write(make_output_folder(tmp_path / "late") / "r.txt", "r")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "ok"]


def test_a_solve_interrupted_while_drawing_its_overlays_leaves_none_of_its_outputs(tmp_path, monkeypatch, capsys):
    """Ctrl-C while the overlays were drawn left some overlays (and, had they come first, the
    report and the model): the command's outputs now appear together or not at all."""
    import mbcal.render.overlays as overlays

    clicks = tmp_path / "clicks.csv"
    plan = ROOT / "measurements" / "lever_plan.csv"
    model = str(ROOT / "models" / "lever.mdl")
    simulate = ["simulate", model, str(plan), "--set", "lever.angle=35deg", "--seed", "1", "-o", str(clicks), "-q"]
    assert main(simulate) == 0
    drawn = overlays.calibration_overlays

    def interrupted(result, folder, **kwargs):
        drawn(result, folder, **kwargs)  # every picture written, then Ctrl-C
        raise KeyboardInterrupt

    monkeypatch.setattr(overlays, "calibration_overlays", interrupted)
    folder = tmp_path / "ov"
    outputs = ["--json", str(tmp_path / "r.json"), "--write-model", str(tmp_path / "m.mdl"), "--overlay", str(folder)]
    assert main(["solve", model, str(clicks), "--estimate", "lever.angle", "-q", *outputs]) == 130
    # nor the overlay folder it made for them (it was left behind, empty)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clicks.csv"]
    monkeypatch.setattr(overlays, "calibration_overlays", drawn)
    assert main(["solve", model, str(clicks), "--estimate", "lever.angle", "-q", *outputs]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["eye_after.png", "eye_before.png"]
    assert (tmp_path / "r.json").is_file() and (tmp_path / "m.mdl").is_file()


def test_the_caches_files_are_not_held_back_with_a_commands_outputs(tmp_path):
    """all_or_nothing held back the cache's writes too: the cache's trimming (a small
    MBCAL_CACHE_MAX_MB) removed their temporary files meanwhile, the rename at the end failed and
    took the command's report with it (exit 2, 'No such file or directory: ….part')."""
    import subprocess
    import sys

    clicks = tmp_path / "clicks.csv"
    model = str(ROOT / "models" / "lever.mdl")
    plan = str(ROOT / "measurements" / "lever_plan.csv")
    env = {**os.environ, "MBCAL_CACHE_DIR": str(tmp_path / "cache"), "MBCAL_CACHE_MAX_MB": "0.01"}
    env.pop("MBCAL_CACHE", None)

    def mbcal(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "mbcal", *args], env=env, capture_output=True, text=True)

    assert mbcal("simulate", model, plan, "--set", "lever.angle=35deg", "-o", str(clicks), "-q").returncode == 0
    done = mbcal("solve", model, str(clicks), "--estimate", "lever.angle", "-q", "--json", str(tmp_path / "r.json"))
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "r.json").is_file()
    assert not [p for p in (tmp_path / "cache").rglob("*.part")]


def test_a_failed_command_removes_only_the_folders_it_made(tmp_path, monkeypatch):
    from mbcal.outputs import all_or_nothing, make_output_folder

    monkeypatch.chdir(tmp_path)
    (tmp_path / "kept").mkdir()  # the user's, empty
    with pytest.raises(KeyboardInterrupt), all_or_nothing():
        make_output_folder("x/../kept/overlays/deeper")  # 'x/..': 'kept' still exists
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"] and not list((tmp_path / "kept").iterdir())
