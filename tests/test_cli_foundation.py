"""`mbcal check` and `mbcal scene` through the real command line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import MODELS


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "mbcal", *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_check_prints_a_summary_of_both_bundled_models():
    result = run("check", str(MODELS / "teleexistence.mdl"), str(MODELS / "arm7.mdl"))
    assert result.returncode == 0, result.stderr
    assert "room.yaw" in result.stdout and "arm.offset7" in result.stdout
    assert "669×453" in result.stdout
    assert "ok: 2 models checked" in result.stdout


def test_check_reports_a_bad_model_with_location_caret_and_exit_2(tmp_path):
    (tmp_path / "bad.mdl").write_text("param a = 1 m\nframe f at rot_z(a)\n")
    result = run("check", "bad.mdl", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.splitlines() == [
        "bad.mdl:2:18: rot_z() angle must be an angle (rad), got a length (m)",
        "    frame f at rot_z(a)",
        "                     ^",
    ]
    assert "Traceback" not in result.stderr


def test_check_of_a_missing_file_exits_2_without_traceback(tmp_path):
    result = run("check", "nothere.mdl", cwd=tmp_path)
    assert result.returncode == 2
    assert "file not found" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize("suffix", ["glb", "obj", "stl"])
def test_scene_exports_a_file_that_trimesh_reads_back(tmp_path, suffix):
    import trimesh

    out = tmp_path / f"room.{suffix}"
    result = run("scene", str(MODELS / "teleexistence.mdl"), "--set", "lever.angle=45deg", "-o", str(out))
    assert result.returncode == 0, result.stderr
    loaded = trimesh.load(out)
    assert loaded.bounds[1][2] > 1.3
    assert not list(tmp_path.glob("*.part"))


def test_scene_refuses_to_overwrite_its_input(tmp_path):
    model = tmp_path / "m.mdl"
    model.write_text("frame f { shape box(1 m, 1 m, 1 m) }\n")
    before = model.read_bytes()
    result = run("scene", str(model), "-o", str(model))
    assert result.returncode == 2
    assert "refusing to overwrite the input file" in result.stderr
    assert model.read_bytes() == before


def test_set_with_unknown_parameter_suggests_names(tmp_path):
    result = run("scene", str(MODELS / "teleexistence.mdl"), "--set", "lever.angel=3deg", "-o", str(tmp_path / "x.glb"))
    assert result.returncode == 2
    assert "lever.angle" in result.stderr


def test_help_lists_commands_with_examples():
    result = run("--help")
    assert result.returncode == 0
    for command in ("check", "scene"):
        assert command in result.stdout
        sub = run(command, "--help")
        assert "example:" in sub.stdout


def test_check_and_help_do_not_import_jax():
    # `mbcal check` is the editor's quick loop: it must not pay for JAX (nor the solver, nor pyrender).
    code = (
        "import sys\n"
        "from mbcal.cli import main\n"
        f"assert main(['check', '-q', {str(MODELS / 'teleexistence.mdl')!r}, {str(MODELS / 'arm7.mdl')!r}]) == 0\n"
        "heavy = sorted(m for m in ('jax', 'pyrender', 'mbcal.solver', 'mbcal.problem') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_the_suite_never_writes_into_the_users_cache_folder():
    """tests/conftest.py points the suite (and the commands it starts) at a cache folder of its
    own unless MBCAL_CACHE_DIR names one: thousands of test programs would fill the user's."""
    import json
    import os
    from pathlib import Path

    from mbcal.cache import cache_dir

    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    assert os.environ.get("MBCAL_CACHE_DIR") and cache_dir() != Path(base) / "mbcal"
    child = run("cache", "--json", "-")
    assert child.returncode == 0 and json.loads(child.stdout)["folder"] == str(cache_dir())


def test_the_program_parts_are_kept_under_their_bound_least_recently_used_first(tmp_path, monkeypatch):
    import os
    import time

    from mbcal.cache import trim_programs
    from mbcal.errors import MbcalError

    cache = tmp_path / "cache"
    (cache / "exports").mkdir(parents=True)
    (cache / "jax").mkdir()
    now = time.time()

    def entry(path, size, used):  # used: seconds ago
        path.write_bytes(b"x" * size)
        os.utime(path, (now - used, now - used))
        return path

    exports = [
        entry(cache / "exports" / (c * 64 + ".jaxexport"), 100, used) for c, used in zip("abcde", [50, 10, 40, 20, 30])
    ]
    # JAX's entries: a program and, with JAX's own eviction on, its access-time file (removed together);
    # "1" was written long ago but read a minute ago (its access time): kept before "2".
    jax = {}
    for c, used in zip("123", [900, 300, 600]):
        jax[c] = [entry(cache / "jax" / f"jit_f-{c * 64}-cache", 200, used)]
    os.utime(jax["1"][0], (now - 60, now - 900))
    jax["3"].append(entry(cache / "jax" / f"jit_f-{'3' * 64}-atime", 8, 600))
    mine = entry(cache / "exports" / "notes.txt", 5000, 1000)  # the user's file, not an entry: never removed

    assert trim_programs(cache, limit=1000).files == 0  # nothing over the bound: nothing removed
    cleared = trim_programs(cache, limit=350)
    # exports: 500 bytes > 350, the least recently used go until 90 % (315) is left: a, then c.
    assert [p.exists() for p in exports] == [False, True, False, True, True]
    # jax: 608 bytes > 350: "3" (used 600 s ago, both files), then "2" (300 s); "1" was read last.
    assert [all(p.exists() for p in jax[c]) for c in "123"] == [True, False, False]
    assert not any(p.exists() for p in jax["3"])
    assert cleared.files == 5 and cleared.bytes == 2 * 100 + 200 + 208 and mine.exists()
    # The entry just written is never removed, even when it alone is over the bound.
    assert trim_programs(cache, limit=10, keep=exports[1]).files == 3
    assert exports[1].exists() and not exports[3].exists() and mine.exists()

    monkeypatch.setenv("MBCAL_CACHE_DIR", str(cache))
    monkeypatch.setenv("MBCAL_CACHE_MAX_MB", "lots")
    with pytest.raises(MbcalError, match="MBCAL_CACHE_MAX_MB='lots': not a positive number"):
        trim_programs()
    bad = run("cache")
    assert bad.returncode == 2 and "MBCAL_CACHE_MAX_MB='lots'" in bad.stderr
    before = sorted(cache.rglob("*"))
    assert run("cache", "--clear").returncode == 2 and sorted(cache.rglob("*")) == before  # said before clearing
    monkeypatch.setenv("MBCAL_CACHE", "off")
    assert run("cache").returncode == 0  # caching off: the bound does not matter
    monkeypatch.delenv("MBCAL_CACHE")
    monkeypatch.setenv("MBCAL_CACHE_MAX_MB", "0.5")
    shown = run("cache")
    assert shown.returncode == 0 and "kept under 512.0 kB" in shown.stdout


def test_exported_programs_are_marked_when_loaded_and_old_ones_removed_when_new_ones_come(tmp_path, monkeypatch):
    import hashlib
    import os

    from mbcal._jax import jax
    from mbcal.cache import exported

    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    key = [hashlib.sha256(name.encode()).hexdigest() for name in ("first", "second")]
    path = [tmp_path / "exports" / f"{k}.jaxexport" for k in key]
    x = jax.numpy.arange(3.0)
    assert float(exported(key[0], jax.jit(lambda v: v + 1), x, keep=False)(x)[2]) == 3.0
    os.utime(path[0], (1, 1))  # as if last used long ago
    assert float(exported(key[0], jax.jit(lambda v: v + 1), x, keep=False)(x)[2]) == 3.0
    assert path[0].stat().st_mtime > 1  # loaded: its use is marked
    size = path[0].stat().st_size
    monkeypatch.setenv("MBCAL_CACHE_MAX_MB", str(1.5 * size / 2**20))  # room for one program
    os.utime(path[0], (1, 1))
    assert float(exported(key[1], jax.jit(lambda v: v * 2), x, keep=False)(x)[2]) == 4.0
    assert path[1].exists() and not path[0].exists()  # the new one written, the old one gone


def test_cache_shows_each_part_and_clears_only_the_files_mbcal_wrote(tmp_path, monkeypatch):
    # `mbcal cache` says what the cache folder holds, --clear empties it — and never touches a
    # file it did not write, since MBCAL_CACHE_DIR may name a folder of the user's.
    import json

    from mbcal.cli import main

    cache = tmp_path / "cache"
    files = {
        "exports": ["a" * 64 + ".jaxexport", "b" * 64 + ".jaxexport", "." + "c" * 64 + ".jaxexport.x1y2.part"],
        "jax": [
            "jit_call-" + "d" * 64 + "-cache",
            "jit_scatter-add-" + "e" * 64 + "-cache",
            "jit_größe-" + "0" * 64 + "-atime",
        ],
        "meshes": ["f" * 64 + ".npz"],
        "lark": ["mdl-grammar.lark"],
        "syntax": ["7" * 64 + ".json"],
    }
    for part, names in files.items():
        (cache / part).mkdir(parents=True)
        for k, name in enumerate(names):
            (cache / part / name).write_bytes(b"x" * (100 + k))
    users = tmp_path / "users.txt"
    users.write_text("the user's")
    mine = [cache / "exports" / "notes.txt", cache / "jax" / "jit_call-short-cache", cache / "my.jaxexport"]
    for path in mine:
        path.write_text("the user's")
    (cache / "meshes" / ("9" * 64 + ".npz")).symlink_to(users)  # named like an entry: a link, kept
    (cache / "exports" / ("8" * 64 + ".jaxexport")).mkdir()  # a folder named like an entry: kept
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(cache))
    monkeypatch.delenv("MBCAL_CACHE", raising=False)

    result = run("cache")
    assert result.returncode == 0, result.stderr
    lines = {line.split()[0]: line.split() for line in result.stdout.splitlines()[3:]}
    assert lines["exports"][1:3] == ["3", "303"] and lines["jax"][1:3] == ["3", "303"]
    assert lines["meshes"][1] == lines["lark"][1] == lines["syntax"][1] == "1" and lines["total"][1] == "9"
    assert str(cache) in result.stdout

    report = tmp_path / "cache.json"
    assert main(["cache", "--clear", "exports", "meshes", "--json", str(report), "-q"]) == 0
    data = json.loads(report.read_text())
    assert data["removed"] == {"files": 4, "bytes": 100 + 101 + 102 + 100, "problems": []}
    left_over = {"exports": 0, "jax": 3, "meshes": 0, "lark": 1, "syntax": 1}
    assert {p["part"]: p["files"] for p in data["parts"]} == left_over
    assert main(["cache", "--clear", "-q"]) == 0
    left = sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if not p.is_dir() or p.name.startswith("8"))
    assert left == sorted(
        ["exports/" + "8" * 64 + ".jaxexport", "meshes/" + "9" * 64 + ".npz"]
        + [str(p.relative_to(cache)) for p in mine]
    )
    assert users.read_text() == "the user's" and all(p.read_text() == "the user's" for p in mine)

    bad = run("cache", "--clear", "everything")
    assert bad.returncode == 2 and "invalid choice" in bad.stderr

    kept = cache / "lark" / "mdl-grammar.lark"
    kept.write_text("tables")
    other = cache / "jax" / ("jit_call-" + "1" * 64 + "-cache")
    other.write_text("program")
    unlink = type(kept).unlink

    def refuse(path, *a, **kw):  # a file the user may not remove (root may remove anything)
        if path == kept:
            raise PermissionError(13, "Permission denied", str(path))
        return unlink(path, *a, **kw)

    monkeypatch.setattr(type(kept), "unlink", refuse)
    assert main(["cache", "--clear", "-q"]) == 2  # named on stderr; the other files still removed
    assert kept.exists() and not other.exists()
    monkeypatch.setattr(type(kept), "unlink", unlink)
    monkeypatch.setenv("MBCAL_CACHE", "off")  # caching off: nothing shown, nothing removed
    off = run("cache", "--clear")
    assert off.returncode == 0 and "caching is off" in off.stdout
    assert kept.read_text() == "tables"


def test_a_cache_folder_that_is_a_file_is_said_not_shown_as_an_empty_cache(tmp_path, monkeypatch):
    """MBCAL_CACHE_DIR naming a regular file: 'mbcal cache' showed an empty cache and exited 0,
    and every other command ran without its caches in silence."""
    from mbcal import cache

    afile = tmp_path / "cache.txt"
    afile.write_text("not a folder\n")
    monkeypatch.delenv("MBCAL_CACHE", raising=False)
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(afile))
    shown = run("cache")
    assert shown.returncode == 2 and shown.stdout == ""
    assert shown.stderr.startswith(f"$MBCAL_CACHE_DIR ({afile}) is not a folder: mbcal cannot keep its cache there")
    checked = run("check", str(MODELS / "lever.mdl"))
    assert checked.returncode == 0
    said = f"warning: the cache is off: $MBCAL_CACHE_DIR ({afile}) is not a folder; nothing is kept between runs"
    assert checked.stderr.count(said) == 1, checked.stderr
    # in Python: None (no cache), said once per process; a folder under a file likewise
    monkeypatch.setattr(cache, "_CACHE_OFF_SAID", set())
    with pytest.warns(cache.CacheOffWarning) as caught:
        assert cache.cache_dir() is None and cache.cache_dir() is None
    assert len(caught) == 1
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(afile / "sub"))
    assert cache.cache_dir_problem() == f"$MBCAL_CACHE_DIR ({afile / 'sub'}) is under {afile}, which is not a folder"
    monkeypatch.setenv("MBCAL_CACHE_DIR", str(tmp_path / "new" / "folder"))  # missing: made when used
    assert cache.cache_dir_problem() is None and cache.cache_dir() == tmp_path / "new" / "folder"
