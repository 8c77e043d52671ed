"""The documentation's examples run: every ```mdl block loads, every ```python block executes."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from mbcal.language import load_model

from conftest import ROOT

DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
FENCE = re.compile(r"^```(\w[\w-]*)([^\n]*)\n(.*?)^```", re.S | re.M)


def blocks(path: Path, language: str) -> list[tuple[int, str, str]]:
    """(line, info string, text) of every fenced block of one language."""
    text = path.read_text(encoding="utf-8")
    out = []
    for m in FENCE.finditer(text):
        if m.group(1) == language:
            out.append((text.count("\n", 0, m.start()) + 1, m.group(2).strip(), m.group(3)))
    return out


MDL_BLOCKS = [(p, line, info, body) for p in DOCS for line, info, body in blocks(p, "mdl")]


@pytest.mark.parametrize("doc, line, info, body", MDL_BLOCKS, ids=[f"{p.name}:{ln}" for p, ln, _, _ in MDL_BLOCKS])
def test_mdl_example_loads(doc, line, info, body, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copytree(ROOT / "models" / "meshes", tmp_path / "meshes")
    # Blocks marked file=NAME are helper files that later examples of the same page include.
    for _, other_info, other_body in blocks(doc, "mdl"):
        if other_info.startswith("file="):
            target = tmp_path / other_info.split("=", 1)[1]
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(other_body, encoding="utf-8")
    (tmp_path / "example.mdl").write_text(body, encoding="utf-8")
    model = load_model("example.mdl")
    assert model is not None


def test_language_reference_has_an_example_for_every_statement():
    text = (ROOT / "docs" / "language.md").read_text(encoding="utf-8")
    examples = "\n".join(body for _, _, body in blocks(ROOT / "docs" / "language.md", "mdl"))
    for keyword in [
        "param",
        "let",
        "template",
        "frame",
        "object",
        "link",
        "shape",
        "point",
        "joint",
        "camera",
        "range",
        "target",
        "include",
        "measure",
        "per configuration",
        "sigma",
        "±",
        "mesh(",
        "tube",
    ]:
        assert keyword in examples, keyword
    for function in ["translate", "rot_x", "rpy", "pose(", "axis_angle", "quat", "look_at", "sqrt", "atan2", "hypot"]:
        assert function in examples, function
    assert "## Errors" in text


def test_the_reserved_words_listed_are_the_languages():
    """The list omitted 'override' (a parameter called so was refused without the page saying so)."""
    from mbcal.language.parse import RESERVED

    text = (ROOT / "docs" / "language.md").read_text(encoding="utf-8")
    section = text.split("## Reserved words and conventions", 1)[1]
    listed = re.search(r"^Reserved \(.*?\): `([^`]*)`", section, re.S | re.M)
    assert listed is not None
    assert sorted(listed.group(1).split()) == sorted(RESERVED)


def removed_names() -> set[str]:
    """The 0.1 names in architecture.md's table of names kept for one release (its first column):
    some are gone, as the table says."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    section = text.split("## Names kept for one release", 1)[1].split("\n## ", 1)[0]
    first = [line.split("|")[1] for line in section.splitlines() if line.startswith("| `")]
    return {name for cell in first for name in re.findall(r"`(mbcal[\w.]*)`", cell)}


def test_every_dotted_mbcal_name_in_the_docs_works_after_a_plain_import():
    """`mbcal.measurements.registry()` (api.md) raised AttributeError after `import mbcal`: the
    package's modules load on first use, none of them at start-up."""
    import subprocess
    import sys

    names = {m.group(0) for doc in DOCS for m in re.finditer(r"\bmbcal(?:\.[A-Za-z_]\w*)+", doc.read_text("utf-8"))}
    names -= removed_names()
    assert "mbcal.measurements.registry" in names and "mbcal.fileio" not in names
    code = f"""
import importlib, sys
import mbcal
assert not any(m.startswith("mbcal.") and m != "mbcal._sources" for m in sys.modules), "import mbcal is not lazy"
for name in {sorted(names)!r}:
    try:
        value = mbcal
        for part in name.split(".")[1:]:
            value = getattr(value, part)
    except Exception as err:
        print(name, type(err).__name__, err)
"""
    result = subprocess.run(
        [sys.executable, "-W", "ignore", "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0 and not result.stdout, result.stdout + result.stderr[-3000:]


PY_DOCS = [p for p in DOCS if blocks(p, "python")]


@pytest.mark.parametrize("doc", PY_DOCS, ids=[p.name for p in PY_DOCS])
@pytest.mark.slow
def test_python_examples_run(doc, tmp_path):
    """A page's ```python blocks run in order, in one process, from the repository root."""
    import subprocess
    import sys

    code = "\n\n".join(body for _, _, body in blocks(doc, "python"))
    script = tmp_path / f"{doc.stem}_examples.py"
    script.write_text(code, encoding="utf-8")
    result = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert result.returncode == 0, result.stderr[-4000:]


@pytest.mark.slow
def test_cli_session_in_the_guide_runs(tmp_path):
    """docs/cli.md's shell session runs as written (in a scratch copy of the repository's data)."""
    import os
    import shutil
    import subprocess

    (sh_block,) = [body for _, _, body in blocks(ROOT / "docs" / "cli.md", "sh")]
    shutil.copytree(ROOT / "models", tmp_path / "models")
    shutil.copytree(ROOT / "measurements", tmp_path / "measurements")
    env = {**os.environ, "PATH": f"{os.path.dirname(os.sys.executable)}:{os.environ.get('PATH', '')}"}
    result = subprocess.run(
        ["bash", "-e", "-c", sh_block], cwd=tmp_path, capture_output=True, text=True, timeout=1200, env=env
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    out = tmp_path / "out"
    for name in (
        "room.csv",
        "report.json",
        "calibrated.mdl",
        "residuals.png",
        "robust.json",
        "left.png",
        "calibrated.glb",
    ):
        assert (out / name).is_file(), name
    assert "observable: rank 6 of 6" in result.stdout
    assert "(exit status 1: not enough)" in result.stdout and "NOT observable" in result.stdout
