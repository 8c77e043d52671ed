"""The wheel carries the grammar, and mbcal finds it there without the source checkout."""

from __future__ import annotations

import subprocess
import sys
import zipfile

from conftest import ROOT


def test_wheel_contains_the_grammar_and_loads_it(tmp_path):
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-w", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    wheel = next(tmp_path.glob("mbcal-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        assert z.read("mbcal/grammar/mdl.lark") == (ROOT / "grammar" / "mdl.lark").read_bytes()
        for name in ("index.html", "studio.js", "studio.css"):  # the studio's page ships in the wheel
            assert z.read(f"mbcal/studio/static/{name}") == (ROOT / "mbcal" / "studio" / "static" / name).read_bytes()
        z.extractall(tmp_path / "site")
    probe = (
        "import mbcal.language.parse as p, mbcal.language as l;"
        "print(p.grammar_path());"
        "print(len(l.load_model_text('param a = 1 m').params))"
    )
    # Run from an empty folder with only the unpacked wheel on the path: no checkout to fall back on.
    out = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        # the suite's cache folder (conftest.py), not the user's
        env={"PYTHONPATH": str(tmp_path / "site"), "PATH": "/usr/bin:/bin", "MBCAL_CACHE_DIR": str(tmp_path / "cache")},
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    grammar, count = out.stdout.split()
    assert grammar.startswith(str(tmp_path / "site"))
    assert count == "1"
