"""The house has one direction (docs/architecture.md): the import-linter contracts hold, no module
of mbcal imports one that imports it back, and docs/architecture.md names every module."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import grimp

from conftest import ROOT


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iteratively)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_no_module_of_mbcal_is_part_of_an_import_cycle():
    # Imports inside functions count too; imports only for type checking do not (they never run).
    graph = grimp.build_graph("mbcal", exclude_type_checking_imports=True)
    assert _cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    class Toy:
        modules = {"a", "b", "c", "d"}
        edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}

        def find_modules_directly_imported_by(self, m):
            return self.edges.get(m, set())

    assert _cycles(Toy()) == [["a", "b", "c"]]


def test_the_layer_contracts_are_kept():
    # import-linter is part of the test extra: its command sits beside this Python.
    exe = Path(sys.executable).parent / "lint-imports"
    proc = subprocess.run([str(exe)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:]
    assert "0 broken" in proc.stdout


def test_the_architecture_guide_names_every_module():
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    named = set(re.findall(r"`(mbcal/[\w/]+\.py)`", text))
    existing = {p.relative_to(ROOT).as_posix() for p in (ROOT / "mbcal").rglob("*.py")}
    # A sub-package's __init__ may be named (when it does more than re-export) but need not be.
    modules = existing - {m for m in existing if m.endswith("__init__.py") and m != "mbcal/__init__.py"}
    assert modules - named == set(), "modules missing from docs/architecture.md"
    assert named - existing == set(), "docs/architecture.md names modules that do not exist"


def test_the_old_documented_module_paths_still_import_with_a_deprecation_warning():
    code = (
        "import warnings\n"
        "warnings.simplefilter('error', DeprecationWarning)\n"
        "for name in ('mbcal.urdf', 'mbcal.calibration', 'mbcal.detect', 'mbcal.measurements.files'):\n"
        "    try:\n"
        "        __import__(name)\n"
        "    except DeprecationWarning as warning:\n"
        "        assert 'deprecated' in str(warning), warning\n"
        "    else:\n"
        "        raise SystemExit(name + ' imported without a warning')\n"
        "warnings.simplefilter('ignore', DeprecationWarning)\n"
        "from mbcal.urdf import urdf_to_mdl, write_urdf, urdf_names, UrdfError\n"
        "from mbcal.calibration import calibrate_cameras, plan_views, synthesize_images\n"
        "from mbcal.detect import detect_images\n"
        "from mbcal.measurements.files import read_measurements, write_measurements, MeasurementSet\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
